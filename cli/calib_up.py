"""``freipose calib up``: store the world's up direction (and floor) with a calibration."""

from __future__ import annotations

from pathlib import Path

import click

from freipose.cli._common import user_errors
from freipose.errors import FreiPoseError


def parse_up(value: str) -> tuple[float, float, float]:
    """``"X,Y,Z"`` -> three floats, not all zero.

    Raises:
        click.BadParameter: not three numbers, or all zero.
    """
    parts = [p for p in value.replace(" ", "").split(",") if p]
    try:
        xyz = tuple(float(p) for p in parts)
    except ValueError:
        xyz = ()
    if len(xyz) != 3 or not any(xyz) or not all(abs(x) < float("inf") for x in xyz):
        raise click.BadParameter(
            f"expected the up direction as three numbers X,Y,Z, not all zero (e.g. 0,-1,0), "
            f"got {value!r}",
            param_hint="--up",
        )
    return (xyz[0], xyz[1], xyz[2])


@click.command("up")
@click.argument("calibration", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--up",
    "up",
    default=None,
    metavar="X,Y,Z",
    help="The up direction in the calibration's world frame.",
)
@click.option(
    "--from-labels",
    "labels",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="Estimate the up direction and the floor from the labeled animal's 3D points "
    "(labels.h5): the plane it moves on, on the side of most cameras.",
)
@click.option(
    "--floor",
    "floor",
    type=float,
    default=None,
    metavar="MM",
    help="The floor's height along the up direction (the floor is up . X = MM).",
)
@click.option(
    "-o",
    "--output",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Where to write the calibration (default: CALIBRATION itself).",
)
def up(
    calibration: Path,
    up: str | None,
    labels: Path | None,
    floor: float | None,
    output: Path | None,
) -> None:
    """Store the world's up direction (and the floor height) in a calibration file.

    Without --origin-frame the world of freipose calib is the first camera's frame, whose
    up direction nobody knows: predict writes it into the poses, training turns the voxel
    grid about it and the analysis measures heights along it. Give it with --up, or
    estimate it from labels whose animal moved over the floor with --from-labels (labels
    triangulated with this calibration).

    \b
    Examples:
      freipose calib up calibration.toml --up 0,-1,0
      freipose calib up calibration.toml --from-labels labels/labels.h5
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    with user_errors():
        import numpy as np

        from freipose.io.calibration import load_calibration, save_calibration
        from freipose.io.calibration_world import WorldUp, up_from_labels, with_world_up
        from freipose.io.labels import read_labels_h5

        if up is not None and labels is not None:
            raise FreiPoseError("pass one of --up X,Y,Z and --from-labels LABELS, not both")
        rig = load_calibration(calibration)
        if up is not None:
            world = WorldUp(np.asarray(parse_up(up)), "given with freipose calib up --up", floor)
        elif labels is not None:
            world = up_from_labels(rig, read_labels_h5(labels).points3d)
            if floor is not None:
                world = WorldUp(world.up, world.source, floor)
        else:
            raise FreiPoseError("pass the up direction with --up X,Y,Z or --from-labels LABELS")
        out = output if output is not None else calibration
        save_calibration(with_world_up(rig, world), out)
        fl = "unknown" if world.floor is None else f"{world.floor:.1f} mm"
        click.echo(
            f"wrote {out}: up = {np.round(world.up, 4).tolist()} ({world.source}); floor {fl}"
        )
