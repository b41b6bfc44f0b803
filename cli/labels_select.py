"""``freipose labels select``: propose the least confident, diverse frames to label next."""

from __future__ import annotations

from pathlib import Path

import click

from freipose.cli._common import (
    calibration_option,
    camera_map_from,
    camera_map_option,
    detection_options,
    detector_spec,
    device_option,
    echo_result,
    frames_option,
    user_errors,
)
from freipose.cli.labels import writing_outputs


@click.command("select")
@click.argument("sessions", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@click.option(
    "--model",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="Pose network checkpoint; sessions without predictions in --poses-dir are predicted.",
)
@click.option(
    "--poses-dir",
    type=click.Path(file_okay=False, path_type=Path),
    help="Folder with <session>.poses.h5 from `freipose predict` (missing ones are predicted "
    "into it with --model) [default: OUTPUT's folder/poses].",
)
@click.option("--n", "n", type=int, default=50, show_default=True, help="Frames per session.")
@click.option(
    "--min-gap",
    type=int,
    default=10,
    show_default=True,
    help="Fewest frames between two proposed frames (and to already labeled ones).",
)
@click.option(
    "--labels",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="labels.h5 whose frames are already labeled (kept --min-gap away).",
)
@click.option(
    "-o",
    "--output",
    type=click.Path(dir_okay=False, path_type=Path),
    default=Path("selection.csv"),
    show_default=True,
    help="CSV: session, frame_index, rank, mean_confidence, found.",
)
@click.option(
    "--extract",
    type=click.Path(file_okay=False, path_type=Path),
    help="Also write the frames as DIR/<session>/<camera>/<frame:08d>.png for labeling.",
)
@calibration_option()
@camera_map_option()
@detection_options
@frames_option("Frame range START:STOP to predict [default: all].")
@click.option("--batch", type=int, default=8, show_default=True, help="Time steps per batch.")
@device_option()
@click.pass_context
def select(
    ctx: click.Context,
    sessions: tuple[Path, ...],
    model: Path | None,
    poses_dir: Path | None,
    n: int,
    min_gap: int,
    labels: Path | None,
    output: Path,
    extract: Path | None,
    calibration: Path | None,
    camera_map: tuple[str, ...],
    detector: Path | None,
    method: str | None,
    fixed_boxes: Path | None,
    min_views: int,
    bg_samples: int,
    frames: str | None,
    batch: int,
    device: str,
) -> None:
    """Propose frames to label next: least confident predictions, diverse in pose and time.

    Uses the predictions in --poses-dir, predicting sessions that have none with --model
    (resumable, like `freipose predict`). Writes a ranked CSV and, with --extract, the
    frames of every camera as PNG files.

    \b
    Examples:
      freipose labels select rec1/ rec2/ --model model.pt --detector det.pt --n 50
      freipose labels select rec1/ --poses-dir poses/ --labels labels.h5 --extract to_label/
    """  # noqa: D301 (click needs the \b escape)
    with user_errors(), writing_outputs(output, what="selection file") as real:
        from freipose.io.labels import read_labels_h5
        from freipose.io.poses import read_poses_h5
        from freipose.io.session import discover_sessions
        from freipose.labels.select import extract_frames, select_frames, write_selection_csv
        from freipose.predict.network import predict_sessions
        from freipose.predict.run import output_path
        from freipose.predict.writer import is_complete

        quiet = bool(ctx.obj and ctx.obj.get("quiet"))
        found = discover_sessions(sessions, calibration, camera_map=camera_map_from(camera_map))
        pdir = poses_dir if poses_dir is not None else output.parent / "poses"
        todo = [s for s in found if not is_complete(output_path(pdir, s.name))]
        if todo:
            if model is None:
                names = [s.name for s in todo]
                raise click.UsageError(
                    f"no predictions for sessions {names} in {pdir}; pass --model CKPT (and how "
                    "to find the animal) to predict them, or --poses-dir with their poses.h5"
                )
            spec = detector_spec(detector, method, fixed_boxes, bg_samples, min_views)
            predict_sessions(
                todo, model, spec, pdir, frames=frames, batch_size=batch, device=device,
                progress=not quiet, report=echo_result,
            )  # fmt: skip
        done_labels = read_labels_h5(labels) if labels is not None else None
        picks = []
        for s in found:
            data = read_poses_h5(output_path(pdir, s.name))
            exclude = ()
            if done_labels is not None:
                exclude = done_labels.frame_index[done_labels.session == s.name]
            sel = select_frames(data, n, min_gap, exclude, session=s.name)
            picks.append(sel)
            low = float(sel.confidence.mean()) if len(sel) else float("nan")
            click.echo(f"{s.name}: {len(sel)} frames proposed (mean confidence {low:.2f})")
            if extract is not None:
                extract_frames(dict(s.videos), sel.frame_index, extract / s.name)
        write_selection_csv(picks, real[0])
        click.echo(f"wrote {output}")
