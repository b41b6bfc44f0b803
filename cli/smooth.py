"""``freipose smooth``: temporal smoothing of poses with a posterior standard deviation."""

from __future__ import annotations

from pathlib import Path

import click

from freipose.cli._common import (
    allow_incomplete_option,
    check_complete,
    overwrite_option,
    user_errors,
)


def smoothed_name(path: Path) -> str:
    """The output file name of a poses file (``x.poses.h5.partial`` -> ``x.poses.h5``)."""
    name = path.name
    return name[: -len(".partial")] if name.endswith(".partial") else name


@click.command()
@click.argument("poses", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@click.option(
    "-o",
    "--outdir",
    required=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Folder for the smoothed <session>.poses.h5 files (not the inputs' folder).",
)
@allow_incomplete_option()
@overwrite_option("smoothed files that exist")
def smooth(poses: tuple[Path, ...], outdir: Path, allow_incomplete: bool, overwrite: bool) -> None:
    """Smooth predicted poses over time, with a standard deviation for every point.

    Each keypoint follows a constant-velocity Kalman smoother whose measurement noise
    grows as the frame's confidence falls; its parameters are fitted on the recording.
    Frames without a prediction are filled (extra/filled), outliers rejected
    (extra/rejected), and extra/smooth_std holds the posterior standard deviation in mm
    per axis. The output has the poses.h5 schema; analyze, export and render read it.

    \b
    Example:
      freipose smooth poses/*.poses.h5 -o poses_smooth/
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    with user_errors():
        from freipose.io.atomic import refuse_existing
        from freipose.predict.smooth import refuse_same, smooth_file

        jobs = [(p, outdir / smoothed_name(p)) for p in dict.fromkeys(poses)]
        for p, _ in jobs:
            check_complete(p, allow_incomplete)
        for p, out in jobs:
            refuse_same(p, out)
            refuse_existing(out, overwrite)
        for p, out in jobs:
            click.echo(f"wrote {smooth_file(p, out, overwrite=overwrite)}")
