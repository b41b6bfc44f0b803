"""``freipose calib``: calibrate cameras from board videos, and calibration-file utilities."""

from __future__ import annotations

import click

from freipose.cli._lazy import DefaultLazyGroup

SUBCOMMANDS = {
    "run": "freipose.cli.calib_run:run",
    "board": "freipose.cli.calib_run:board",
    "convert": "freipose.cli.calib_files:convert",
    "show": "freipose.cli.calib_files:show",
    "up": "freipose.cli.calib_up:up",
}


@click.group(cls=DefaultLazyGroup, default="run", lazy_commands=SUBCOMMANDS)
def calib() -> None:
    """Calibrate cameras from synchronized board videos, or convert/show calibration files.

    A calibration that is not physically plausible (a field of view, principal point or
    distortion no lens has, a camera whose board poses disagree with the others' or whose
    detections the rig explains much worse than the camera alone, over 30 % of a camera's
    detections beyond its own noise level, a focal length the views do not pin down) is not
    written: the message names the camera, the numbers and the fix; --force writes it marked
    as suspect (see freipose calib run --help). --intrinsics-from takes intrinsics from a
    separate recording.

    Boards printed inverted (white squares and markers on black) need `inverted = true` in
    the board file; the message for a board that is never found says so when the images
    show one. A board seen from behind (a camera under a transparent floor, a board printed
    on both sides or on a transparent sheet) is found without being told: ChArUco boards and
    AprilGrids are searched in the mirror image, and the output says how many frames each
    camera saw from behind. A chessboard seen from behind cannot be told from a mirrored
    grid: use a ChArUco board or an AprilGrid for such rigs.

    The world's up direction is stored with the calibration: z with --origin-frame N (the
    board on the floor in frame N), the direction given with --up X,Y,Z, or later with
    freipose calib up (given, or estimated from the labeled animal). Without it, the later
    steps estimate it from the labels or assume z and warn.

    \b
    Examples:
      freipose calib cams/cam0.mp4 cams/cam1.mp4 --board board.toml -o calibration.toml
      freipose calib show calibration.toml
      freipose calib up calibration.toml --up 0,-1,0
      freipose calib convert calibration.toml M.json
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
