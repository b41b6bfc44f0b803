"""``freipose calib``: calibrate cameras from board videos, and calibration-file utilities."""

from __future__ import annotations

import click

from freipose.cli._lazy import DefaultLazyGroup

SUBCOMMANDS = {
    "run": "freipose.cli.calib_run:run",
    "board": "freipose.cli.calib_run:board",
    "convert": "freipose.cli.calib_files:convert",
    "show": "freipose.cli.calib_files:show",
}


@click.group(cls=DefaultLazyGroup, default="run", lazy_commands=SUBCOMMANDS)
def calib() -> None:
    """Calibrate cameras from synchronized board videos, or convert/show calibration files.

    \b
    Examples:
      freipose calib cams/cam0.mp4 cams/cam1.mp4 --board board.toml -o calibration.toml
      freipose calib show calibration.toml
      freipose calib convert calibration.toml M.json
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
