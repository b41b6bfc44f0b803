"""``freipose labels``: import labels from other tools, check, merge, split and export them."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import click

from freipose.cli._common import user_errors
from freipose.cli._lazy import LazyGroup

if TYPE_CHECKING:
    from freipose.skeleton import Skeleton

SUBCOMMANDS = {
    "import": "freipose.cli.labels:import_labels",
    "check": "freipose.cli.labels:check",
    "merge": "freipose.cli.labels:merge",
    "split": "freipose.cli.labels:split",
    "export": "freipose.cli.labels:export",
    "boxes": "freipose.cli.labels:boxes",
    "select": "freipose.cli.labels_select:select",
}

FORMATS = ("dlc", "sleap", "anipose", "dannce", "jarvis", "freipose")


@click.group(cls=LazyGroup, lazy_commands=SUBCOMMANDS)
def labels() -> None:
    """Labels: import from other tools, find mislabels, merge, split and export.

    \b
    Examples:
      freipose labels import --format dlc project/ --calibration calibration.toml -o labels.h5
      freipose labels check labels.h5 --report check/
      freipose labels split labels.h5 --eval 0.3 -o train.h5 eval.h5
      freipose labels split labels.h5 --by time --gap 50 -o train.h5 eval.h5
    """  # noqa: D301 (click needs the \b escape)


@contextlib.contextmanager
def writing_outputs(*outputs: Path, what: str = "labels file") -> Iterator[list[Path]]:
    """Hold the labels-file lock of every output for the command; yield their real paths.

    Taken before the work, so that a file in use (by a ``freipose label`` server) is
    refused at once and nothing is written.
    """
    from freipose.io.labels import labels_file_lock

    if len({o.resolve() for o in outputs}) < len(outputs):
        raise click.BadParameter(
            f"the outputs {[str(o) for o in outputs]} are one file; name different files",
            param_hint="-o",
        )
    with contextlib.ExitStack() as stack:
        yield [stack.enter_context(labels_file_lock(o, what)) for o in outputs]


def _load_skeleton(spec: str | None) -> Skeleton | None:
    """The skeleton named or stored at ``spec`` (None: no skeleton)."""
    if spec is None:
        return None
    from freipose.skeleton import load_skeleton

    return load_skeleton(spec)


@click.command("import")
@click.argument("sources", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@click.option("--format", "fmt", type=click.Choice(FORMATS), required=True, help="Source tool.")
@click.option(
    "--calibration",
    type=click.Path(exists=True, path_type=Path),
    help="Cameras (any calibration format; see `freipose calib convert`). Without it, "
    "the source's own cameras (DANNCE, SLEAP sessions, Anipose, JARVIS, M.json) or none "
    "(2D-only import, no triangulation).",
)
@click.option(
    "--calibration-format", default=None, help="Format of --calibration (default: by suffix)."
)
@click.option(
    "--skeleton",
    default=None,
    help="Skeleton name (rat, mouse, paw) or TOML file; defines keypoint names and order. "
    "Default: the source's keypoint names.",
)
@click.option("--map", "maps", multiple=True, metavar="OLD=NEW", help="Rename a keypoint.")
@click.option(
    "--camera-map", "camera_maps", multiple=True, metavar="OLD=NEW", help="Rename a camera."
)
@click.option(
    "--mapping",
    "mapping_file",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="Mapping file ([keypoints] and [cameras] tables; docs/formats.md).",
)
@click.option("--session", default=None, help="Session name for all imported labels.")
@click.option(
    "--instances",
    type=click.Choice(["user", "predicted", "all"]),
    default=None,
    help="SLEAP only: import user-labeled instances (default), predictions (predicted; e.g. "
    "proofread ones) or both (all: predictions where a frame has no user instance). The "
    "labels file records the choice.",
)
@click.option(
    "--threshold",
    type=float,
    default=20.0,
    show_default=True,
    help="RANSAC inlier threshold (px) for triangulating 2D labels.",
)
@click.option("--ignore-unknown", is_flag=True, help="Drop source keypoints the skeleton lacks.")
@click.option("--skip-empty", is_flag=True, help="Drop rows without any label (else: error).")
@click.option(
    "-o",
    "--output",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    help="labels.h5 to write.",
)
def import_labels(
    sources: tuple[Path, ...],
    fmt: str,
    calibration: Path | None,
    calibration_format: str | None,
    skeleton: str | None,
    maps: tuple[str, ...],
    camera_maps: tuple[str, ...],
    mapping_file: Path | None,
    session: str | None,
    instances: str | None,
    threshold: float,
    ignore_unknown: bool,
    skip_empty: bool,
    output: Path,
) -> None:
    """Import labels from DeepLabCut, SLEAP, Anipose, DANNCE, JARVIS or original FreiPose.

    2D labels seen in at least two calibrated views are triangulated robustly (RANSAC over
    views, then refinement); single-view labels stay 2D only. Nothing is written on error.
    SLEAP: one .slp per camera (file stems or --camera-map name the cameras) or a session
    folder session/<camera>/*.slp (cameras from the folder names).

    \b
    Examples:
      freipose labels import --format dlc labeled-data/run1_cam0 labeled-data/run1_cam1 \\
          --calibration calibration.toml --skeleton rat --map snout=Nose -o labels.h5
      freipose labels import --format dannce label3d_dannce.mat -o labels.h5
      freipose labels import --format sleap session.slp -o labels.h5
      freipose labels import --format sleap session1/ --instances predicted \\
          --calibration calibration.toml -o labels.h5
    """  # noqa: D301 (click needs the \b escape)
    with user_errors(), writing_outputs(output) as real:
        from freipose.io.calibration import load_calibration
        from freipose.io.labels import write_labels_h5
        from freipose.labels.formats import IMPORTERS
        from freipose.labels.importing import ImportOptions, build_labelset
        from freipose.labels.mapping import NameMapping, load_mapping_file, parse_map_options

        mapping = load_mapping_file(mapping_file) if mapping_file else NameMapping()
        mapping = mapping.merged(
            NameMapping(
                parse_map_options(maps, "--map"), parse_map_options(camera_maps, "--camera-map")
            )
        )
        rig = load_calibration(calibration, calibration_format) if calibration else None
        skel = _load_skeleton(skeleton)
        if instances is not None and fmt != "sleap":
            raise click.BadParameter(
                f"--instances applies to --format sleap only (got --format {fmt})",
                param_hint="--instances",
            )
        if fmt == "sleap":
            from freipose.labels.sleap import read_sleap

            srcs = read_sleap(list(sources), rig, mapping, session, instances or "user")
        else:
            srcs = IMPORTERS[fmt](list(sources), rig, mapping, session)
        opts = ImportOptions(
            skeleton_keypoints=tuple(skel.keypoints) if skel is not None else None,
            mapping=mapping,
            calibration=rig,
            calibration_source=str(calibration),
            ignore_unknown=ignore_unknown,
            skip_empty=skip_empty,
            threshold=threshold,
        )
        result = build_labelset(srcs, opts, output)
        write_labels_h5(result, real[0], lock=False)
        import numpy as np

        n3 = int(np.isfinite(result.points3d).all(-1).sum())
        n2 = int(np.isfinite(result.points2d).all(-1).sum())
        click.echo(
            f"wrote {output}: {len(result)} labeled instants, {len(result.sessions)} sessions, "
            f"cameras {list(result.cameras)}, {len(result.keypoints)} keypoints, "
            f"{n2} 2D labels, {n3} 3D points"
        )


@click.command()
@click.argument("labels_file", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--report",
    type=click.Path(file_okay=False, path_type=Path),
    help="Folder for suspicious.csv, reprojection_errors.csv, figures and crops.",
)
@click.option("--skeleton", default=None, help="Skeleton for limbs and left/right pairs.")
@click.option(
    "--max-error",
    type=float,
    default=10.0,
    show_default=True,
    help="Reprojection error (px) above which a label is suspicious.",
)
@click.option(
    "--limb-tolerance",
    type=float,
    default=0.3,
    show_default=True,
    help="Relative limb-length deviation from the dataset median that is suspicious.",
)
@click.option("--top", type=int, default=20, show_default=True, help="How many to print/crop.")
def check(
    labels_file: Path,
    report: Path | None,
    skeleton: str | None,
    max_error: float,
    limb_tolerance: float,
    top: int,
) -> None:
    """Find mislabeled points: reprojection errors, swapped left/right, odd limb lengths.

    Prints the suspicious labels worst first; with --report also writes them as CSV with
    every label's reprojection error, error figures per keypoint and camera, and crops of
    the worst labels (red circle: label, green cross: reprojection) when videos exist.

    \b
    Example:
      freipose labels check labels.h5 --skeleton rat --report check/
    """  # noqa: D301 (click needs the \b escape)
    with user_errors():
        import numpy as np

        from freipose.io.labels import read_labels_h5
        from freipose.labels.check import check_labels, write_report

        lab = read_labels_h5(labels_file)
        res = check_labels(lab, _load_skeleton(skeleton), max_error, limb_tolerance)
        e = res.errors[np.isfinite(res.errors)]
        if len(e):
            click.echo(
                f"{len(e)} labels with a 3D point: reprojection error median "
                f"{np.median(e):.2f} px, 95% {np.percentile(e, 95):.2f} px, max {e.max():.2f} px"
            )
        else:
            click.echo("no label has a 3D point (2D-only labels): no reprojection errors")
        click.echo(f"{len(res.suspicious)} suspicious labels")
        for r, s in enumerate(res.suspicious[:top], start=1):
            where = f"{s.session} frame {s.frame_index}" + (f" {s.camera}" if s.camera else "")
            click.echo(f"{r:4d}. [{s.kind}] {where} {s.keypoint}: {s.detail}")
        if report is not None:
            files = write_report(lab, res, report, labels_file.resolve().parent, top)
            click.echo(f"wrote {len(files)} files to {report}")


@click.command()
@click.argument(
    "inputs", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path)
)
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True)
def merge(inputs: tuple[Path, ...], output: Path) -> None:
    """Merge labels files (union of sessions, cameras and keypoints).

    \b
    Example:
      freipose labels merge a.h5 b.h5 -o all.h5
    """  # noqa: D301 (click needs the \b escape)
    with user_errors(), writing_outputs(output) as real:
        from freipose.io.labels import read_labels_h5, write_labels_h5
        from freipose.labels.ops import merge_labels, rebase_videos

        parts = [rebase_videos(read_labels_h5(p), p.parent, output.parent) for p in inputs]
        res = merge_labels(parts, [str(p) for p in inputs])
        write_labels_h5(res, real[0], lock=False)
        click.echo(f"wrote {output}: {len(res)} labeled instants, {len(res.sessions)} sessions")


@click.command()
@click.argument("labels_file", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--by",
    type=click.Choice(["session", "group", "time"]),
    default="session",
    show_default=True,
    help="Keep whole sessions (or groups of sessions, see --group-pattern) together, or hold "
    "out contiguous time blocks of every session (time; works on one recording).",
)
@click.option(
    "--gap",
    type=int,
    default=50,
    show_default=True,
    help="--by time: frames between a held-out instant and the nearest training instant "
    "(training instants closer to a held-out one are dropped).",
)
@click.option(
    "--blocks",
    type=int,
    default=1,
    show_default=True,
    help="--by time: held-out blocks per session.",
)
@click.option(
    "--group-pattern", default=None, help="Regex: its match in a session name is the group."
)
@click.option("--eval", "eval_fraction", type=float, default=0.3, show_default=True)
@click.option("--eval-sessions", default=None, help="Comma-separated eval sessions/groups.")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option(
    "-o",
    "--output",
    nargs=2,
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    metavar="TRAIN EVAL",
)
def split(
    labels_file: Path,
    by: str,
    group_pattern: str | None,
    eval_fraction: float,
    eval_sessions: str | None,
    seed: int,
    gap: int,
    blocks: int,
    output: tuple[Path, Path],
) -> None:
    """Split into training and evaluation sets that never share a recording or a moment.

    Why not random frames: neighbouring video frames are near-copies of each other, so a
    network evaluated on frames drawn at random between its training frames is tested on
    what it has almost seen, and the error it shows is lower than on a new recording.
    Split by session (or group of sessions), or, with one recording, by time: --by time
    holds out contiguous blocks (--eval of each session's labeled frames, with all
    animals of a frame, in --blocks blocks) and drops the training instants within --gap
    frames of them.

    \b
    Examples:
      freipose labels split labels.h5 --by session --eval 0.3 -o train.h5 eval.h5
      freipose labels split labels.h5 --by time --gap 50 --eval 0.25 -o train.h5 eval.h5
    """  # noqa: D301 (click needs the \b escape)
    with user_errors(), writing_outputs(*output) as real:
        from freipose.io.labels import read_labels_h5, write_labels_h5
        from freipose.labels.ops import rebase_videos, split_by_time, split_labels

        if by == "group" and not group_pattern:
            raise click.BadParameter("--by group needs --group-pattern", param_hint="--by")
        lab = read_labels_h5(labels_file)
        chosen = [s.strip() for s in eval_sessions.split(",")] if eval_sessions else None
        if by == "time":
            tr, ev, groups = split_by_time(lab, eval_fraction, gap, blocks, seed)
        else:
            tr, ev, groups = split_labels(
                lab, eval_fraction, group_pattern if by == "group" else None, chosen, seed
            )
        tr = rebase_videos(tr, labels_file.parent, output[0].parent)
        ev = rebase_videos(ev, labels_file.parent, output[1].parent)
        write_labels_h5(tr, real[0], lock=False)
        try:
            write_labels_h5(ev, real[1], lock=False)
        except BaseException:
            real[0].unlink(missing_ok=True)
            raise
        dropped = len(lab) - len(tr) - len(ev)
        click.echo(
            f"train {output[0]}: {len(tr)} labels; eval {output[1]}: {len(ev)} labels "
            f"({len(ev) / len(lab):.0%}) from {groups}"
            + (f"; {dropped} labels within --gap {gap} frames of them dropped" if dropped else "")
        )


@click.command()
@click.argument("labels_file", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--format", "fmt", type=click.Choice(["dlc", "anipose", "freipose"]), required=True)
@click.option(
    "-o",
    "--output",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="New or empty folder.",
)
@click.option("--scorer", default="freipose", show_default=True, help="DLC scorer name.")
def export(labels_file: Path, fmt: str, output: Path, scorer: str) -> None:
    """Export labels for DeepLabCut, Anipose or the original FreiPose (round trip back).

    \b
    Example:
      freipose labels export labels.h5 --format dlc -o dlc_labels/
    """  # noqa: D301 (click needs the \b escape)
    with user_errors():
        from freipose.io.labels import read_labels_h5
        from freipose.labels.ops import export_labels

        lab = read_labels_h5(labels_file)
        files = export_labels(lab, output, fmt, labels_file.resolve().parent, scorer)
        click.echo(f"wrote {len(files)} files to {output}")


@click.command()
@click.argument("labels_file", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--calibration",
    type=click.Path(exists=True, path_type=Path),
    help="Cameras to make boxes for (default: the labels' first calibrated session).",
)
@click.option(
    "--margin",
    type=float,
    default=0.1,
    show_default=True,
    help="Added on every side, as a fraction of the box's longer side.",
)
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True)
def boxes(labels_file: Path, calibration: Path | None, margin: float, output: Path) -> None:
    """Fixed boxes from the labels: where the labeled animal was in every camera.

    Each camera's box holds every labeled keypoint of the labels (2D labels and projected
    3D labels) plus --margin, centred on the projection of the labels' median centre. For
    a new rig whose detector is untrained and whose animal rests (background subtraction
    needs motion): `freipose predict --fixed-boxes OUTPUT` (predict's --method auto derives
    the same boxes from the model's training labels by itself when nothing else works).

    \b
    Example:
      freipose labels boxes train.h5 -o fixed_boxes.toml
    """  # noqa: D301 (click needs the \b escape)
    with user_errors(), writing_outputs(output, what="boxes file") as real:
        from freipose.detect.label_boxes import label_boxes, write_fixed_boxes
        from freipose.io.calibration import load_calibration
        from freipose.io.labels import read_labels_h5
        from freipose.labels.ops import LabelsOpError

        lab = read_labels_h5(labels_file)
        rig = load_calibration(calibration) if calibration else None
        rig = rig or next((i.calibration for i in lab.sessions.values() if i.calibration), None)
        if rig is None:
            raise LabelsOpError(f"{labels_file} has no calibrated session; pass --calibration FILE")
        res = label_boxes(lab, rig, margin)
        write_fixed_boxes(res, real[0], str(labels_file))
        for cam, b in res.boxes.items():
            click.echo(f"{cam}: [{', '.join(f'{v:.0f}' for v in b)}]")
        click.echo(f"wrote {output}: boxes for {len(res.boxes)} of {len(rig)} cameras")
