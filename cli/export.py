"""``freipose export``: convert ``poses.h5`` to CSV, Anipose CSV, DLC-3D CSV or NWB."""

from __future__ import annotations

import datetime
from pathlib import Path

import click

from freipose.cli._common import user_errors


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
    type=click.Choice(["csv", "anipose", "dlc3d", "nwb"]),
    default="csv",
    show_default=True,
    help="csv: tidy table (one row per frame, <keypoint>_x/_y/_z/_confidence); anipose: "
    "Anipose pose-3d CSV; dlc3d: DeepLabCut-3D style CSV; nwb: NWB with ndx-pose "
    "(needs pip install 'freipose[nwb]').",
)
@click.option(
    "-o",
    "--output",
    type=click.Path(path_type=Path),
    default=None,
    help="Output file (one input), or folder (several inputs, or a name without suffix). "
    "Default: next to each input, "
    "<session>.csv / .anipose.csv / .dlc3d.csv / .nwb.",
)
@click.option(
    "--start-time",
    default=None,
    help="NWB only: recording start as an ISO time with time zone (default 1970-01-01 UTC).",
)
@click.option("--description", default=None, help="NWB only: session description.")
def export(
    poses: tuple[Path, ...],
    fmt: str,
    output: Path | None,
    start_time: str | None,
    description: str | None,
) -> None:
    """Export predicted poses (poses.h5) to formats other tools read.

    Units stay millimetres in the calibration's world frame.

    \b
    Examples:
      freipose export poses/rec1.poses.h5 --format csv
      freipose export poses/*.poses.h5 --format nwb -o nwb/ --start-time 2024-05-01T10:00:00+02:00
      freipose export poses/rec1.poses.h5 --format anipose -o rec1_3d.csv
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    with user_errors():
        from freipose.io.export import default_output, export_poses

        kwargs = {}
        if fmt == "nwb":
            t = _parse_time(start_time)
            if t is not None:
                kwargs["session_start_time"] = t
            if description:
                kwargs["session_description"] = description
        for p in poses:
            if output is None:
                out = None
            elif len(poses) > 1 or output.is_dir() or not output.suffix:
                out = output / default_output(p, fmt).name
            else:
                out = output
            written = export_poses(p, fmt, out, **kwargs)
            click.echo(f"wrote {written}")
