"""``freipose export``: convert ``poses.h5`` to CSV, Anipose CSV, DLC-3D CSV, NWB or movement."""

from __future__ import annotations

import datetime
from pathlib import Path

import click

from freipose.cli._common import (
    allow_incomplete_option,
    check_complete,
    overwrite_option,
    user_errors,
)
from freipose.errors import FreiPoseError


def _parse_time(value: str | None) -> datetime.datetime | None:
    if value is None:
        return None
    try:
        t = datetime.datetime.fromisoformat(value)
    except ValueError:
        raise click.BadParameter(
            f"expected an ISO time such as 2024-05-01T10:00:00+02:00, got {value!r}",
            param_hint="--start-time",
        ) from None
    if t.tzinfo is None:
        raise click.BadParameter(
            f"{value!r} has no time zone; add one, e.g. {value}+00:00", param_hint="--start-time"
        )
    return t


@click.command()
@click.argument("poses", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@click.option(
    "--format",
    "fmt",
    type=click.Choice(["csv", "anipose", "dlc3d", "nwb", "movement"]),
    default="csv",
    show_default=True,
    help="csv: wide table, one row per frame (frame, time_s, <keypoint>_x_mm/_y_mm/_z_mm/"
    "_confidence; spaces in names as _), units and layout in <file>.csv.json; anipose: "
    "Anipose pose-3d CSV; dlc3d: DeepLabCut-3D style CSV; nwb: NWB with ndx-pose "
    "(needs pip install 'freipose[nwb]'); movement: movement's netCDF poses dataset (.nc; "
    "needs pip install 'freipose[movement]').",
)
@click.option(
    "-o",
    "--output",
    type=click.Path(path_type=Path),
    default=None,
    help="Output file (one input), or folder (several inputs, or a name without suffix). "
    "Default: next to each input, "
    "<session>.csv / .anipose.csv / .dlc3d.csv / .nwb / .nc.",
)
@click.option(
    "--start-time",
    default=None,
    help="NWB only: recording start as an ISO time with time zone (default 1970-01-01 UTC).",
)
@click.option("--description", default=None, help="NWB only: session description.")
@click.option(
    "--animal",
    default=None,
    help="Poses of several animals: export only this one (its name in the poses' "
    "individuals). Default: every animal (csv: one row per frame and animal; dlc3d: the "
    "individuals header row; nwb: one PoseEstimation per animal; movement: its individuals "
    "dimension; anipose holds one animal and needs --animal).",
)
@allow_incomplete_option()
@overwrite_option("existing exports")
def export(
    poses: tuple[Path, ...],
    fmt: str,
    output: Path | None,
    start_time: str | None,
    description: str | None,
    animal: str | None,
    allow_incomplete: bool,
    overwrite: bool,
) -> None:
    """Export predicted poses (poses.h5) to formats other tools read.

    Units stay millimetres in the calibration's world frame. An unfinished prediction
    (a .partial file) is refused unless --allow-incomplete, and an existing export is
    kept unless --overwrite.

    \b
    Examples:
      freipose export poses/rec1.poses.h5 --format csv
      freipose export poses/*.poses.h5 --format nwb -o nwb/ --start-time 2024-05-01T10:00:00+02:00
      freipose export poses/rec1.poses.h5 --format anipose -o rec1_3d.csv
      freipose export poses/pair.poses.h5 --format movement
      freipose export poses/pair.poses.h5 --format anipose --animal mouse1
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    with user_errors():
        from freipose.io.atomic import refuse_existing
        from freipose.io.export import export_poses

        kwargs = {}
        if fmt == "nwb":
            t = _parse_time(start_time)
            if t is not None:
                kwargs["session_start_time"] = t
            if description:
                kwargs["session_description"] = description
        jobs = _export_jobs(poses, fmt, output)
        for p, _ in jobs:
            check_complete(p, allow_incomplete)
        for _, out in jobs:
            refuse_existing(out, overwrite)
        for p, out in jobs:
            written = export_poses(p, fmt, out, animal=animal, **kwargs)
            click.echo(f"wrote {written}")


def _export_jobs(poses: tuple[Path, ...], fmt: str, output: Path | None) -> list[tuple[Path, Path]]:
    """``(input, output)`` per distinct input; two inputs with one output are an error."""
    from freipose.io.export import default_output

    inputs = list(dict.fromkeys(p.resolve() for p in poses))
    given: dict[Path, Path] = {}
    for p in poses:
        given.setdefault(p.resolve(), p)
    seen: dict[Path, Path] = {}
    jobs = []
    for key in inputs:
        p = given[key]
        if output is None:
            out = default_output(p, fmt)
        elif len(poses) > 1 or output.is_dir() or not output.suffix:
            out = output / default_output(p, fmt).name
        else:
            out = output
        if out.resolve() in seen:
            raise FreiPoseError(
                f"{seen[out.resolve()]} and {p} would both be exported to {out}; export them "
                "into different folders"
            )
        seen[out.resolve()] = p
        jobs.append((p, out))
    return jobs
