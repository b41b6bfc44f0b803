"""``freipose predict``: synchronized videos -> 3D poses in ``<session>.poses.h5``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from freipose.cli._common import user_errors


def detection_options(f: Any) -> Any:
    """The options that say how to find the animal (shared with ``labels select``)."""
    opts = [
        click.option(
            "--detector",
            type=click.Path(exists=True, dir_okay=False, path_type=Path),
            help="Box detector checkpoint (from `freipose train CONFIG --stage detector`).",
        ),
        click.option(
            "--method",
            type=click.Choice(["detector", "bgsub", "fixed"]),
            help="How to find the animal [default: detector with --detector, fixed with "
            "--fixed-boxes]; bgsub = background subtraction (static cameras, one animal).",
        ),
        click.option(
            "--fixed-boxes",
            type=click.Path(exists=True, dir_okay=False, path_type=Path),
            help="TOML with a [boxes] table: camera = [x0, y0, x1, y1] (for --method fixed).",
        ),
        click.option(
            "--min-views", type=int, default=2, show_default=True, help="Fewest agreeing views."
        ),
        click.option(
            "--bg-samples",
            type=int,
            default=40,
            show_default=True,
            help="Frames for the bgsub background.",
        ),
    ]
    for opt in reversed(opts):
        f = opt(f)
    return f


def detector_spec(
    detector: Path | None,
    method: str | None,
    fixed_boxes: Path | None,
    bg_samples: int,
    min_views: int,
) -> Any:
    from freipose.predict.network import DetectorSpec

    if method is None:
        if detector is not None and fixed_boxes is not None:
            raise ValueError("give either --detector or --fixed-boxes, not both")
        method = "fixed" if fixed_boxes is not None else "detector"
    return DetectorSpec(method, detector, fixed_boxes, bg_samples, min_views)


def echo_result(res: Any) -> None:
    if res.skipped:
        click.echo(f"{res.path}: complete, skipped (use --overwrite to redo it)")
        return
    fps = res.frames / res.seconds if res.seconds > 0 else float("nan")
    counts = ", ".join(f"{v} {k}" for k, v in res.status_counts.items() if v)
    click.echo(
        f"{res.path}: {counts} ({res.frames} frames in {res.seconds:.1f} s, {fps:.1f} frames/s)"
    )
    for cam, i in res.missing.items():
        click.echo(
            f"  warning: camera {cam}: frames from {i} on could not be decoded (truncated video?)",
            err=True,
        )


@click.command()
@click.argument("sessions", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@click.option(
    "--model",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    required=True,
    help="Pose network checkpoint (model.pt from `freipose train`).",
)
@click.option(
    "-o",
    "--outdir",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="Output folder; each session gives OUTDIR/<session>.poses.h5.",
)
@click.option(
    "--calibration",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="Calibration for every session [default: calibration.toml in each session folder].",
)
@detection_options
@click.option("--frames", help="Frame range START:STOP (Python slice, e.g. 0:1000) [default: all].")
@click.option("--batch", type=int, default=8, show_default=True, help="Time steps per batch.")
@click.option("--device", default="auto", show_default=True, help="cpu, cuda, cuda:N or auto.")
@click.option(
    "--refine/--no-refine",
    default=True,
    show_default=True,
    help="Report the refined pose (P1) or the 3D network's initial pose (P0).",
)
@click.option(
    "--shard",
    help="I/N: process only the I-th (0-based) of N contiguous parts of the frames; join the "
    "parts with `freipose merge`.",
)
@click.option(
    "--skeleton",
    help="Expected skeleton (name or TOML); fail early if the model predicts other keypoints.",
)
@click.option("--overwrite", is_flag=True, help="Redo outputs that exist and are complete.")
@click.pass_context
def predict(
    ctx: click.Context,
    sessions: tuple[Path, ...],
    model: Path,
    outdir: Path,
    calibration: Path | None,
    detector: Path | None,
    method: str | None,
    fixed_boxes: Path | None,
    min_views: int,
    bg_samples: int,
    frames: str | None,
    batch: int,
    device: str,
    refine: bool,
    shard: str | None,
    skeleton: str | None,
    overwrite: bool,
) -> None:
    """Predict 3D poses from synchronized videos of one or more sessions.

    A SESSION is a folder with one video per camera (file stem = camera name in the
    calibration), or the video files of one session. Every input is checked before any
    work starts. Outputs are written in chunks: a killed run started again with the same
    command continues where it stopped, and finished outputs are skipped (--overwrite
    redoes them). Frames where the animal is not found hold NaN with confidence 0.

    \b
    Examples:
      freipose predict rec1/ rec2/ --model runs/small/model.pt \\
          --detector runs/det/detector.pt -o poses/
      freipose predict rec1/ --model model.pt --method bgsub --frames 0:3000 -o poses/
      # SLURM array of 8: each task one part, then join them
      freipose predict rec1/ --model model.pt --detector det.pt -o poses/ \\
          --shard $SLURM_ARRAY_TASK_ID/8
      freipose merge poses/
    """
    with user_errors():
        from freipose.predict.network import predict_sessions
        from freipose.predict.run import parse_shard
        from freipose.predict.session import discover_sessions
        from freipose.skeleton import load_skeleton

        quiet = bool(ctx.obj and ctx.obj.get("quiet"))
        if batch < 1:
            raise ValueError(f"--batch must be at least 1, got {batch}")
        shard_t = parse_shard(shard)
        spec = detector_spec(detector, method, fixed_boxes, bg_samples, min_views)
        found = discover_sessions(sessions, calibration)
        predict_sessions(
            found,
            model,
            spec,
            outdir,
            frames=frames,
            batch_size=batch,
            device=device,
            refine=refine,
            shard=shard_t,
            overwrite=overwrite,
            expected_skeleton=load_skeleton(skeleton) if skeleton else None,
            progress=not quiet,
            report=echo_result,
        )
