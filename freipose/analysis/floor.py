"""The floor plane of an arena: the world ``z = 0`` plane, a robust fit to the paws, or a file.

A floor is the plane ``{X : normal · X = offset}`` with a unit ``normal`` pointing up (into
the half space where the animal is); the signed distance of a point to the floor is
``normal · X - offset`` (millimetres, positive above the floor).

Floor file (TOML, see ``docs/formats.md``)::

    normal = [0.0, 0.0, 1.0]   # up-pointing unit normal (world frame)
    offset = 0.0               # mm; the plane is normal . X = offset
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from freipose.errors import FreiPoseError
from freipose.geometry.floor import fit_plane_below
from freipose.io.atomic import atomic_write_text
from freipose.io.toml import check_keys, read_toml

log = logging.getLogger(__name__)


class FloorError(FreiPoseError):
    """A floor file or a floor fit is invalid; the message says why."""


@dataclass(frozen=True, eq=False)
class FloorPlane:
    """A plane ``normal · X = offset`` with a unit normal pointing up.

    Attributes:
        normal: (3,) unit normal (world frame), pointing up.
        offset: signed distance of the plane from the world origin along ``normal`` (mm).
        source: how the plane was obtained (``"world"``, ``"auto"`` or a file path).
    """

    normal: np.ndarray
    offset: float = 0.0
    source: str = "world"

    def __post_init__(self) -> None:
        """Check the plane and scale it to a unit normal."""
        n = np.asarray(self.normal, dtype=np.float64).reshape(-1)
        if n.shape != (3,) or not np.isfinite(n).all() or np.linalg.norm(n) < 1e-12:
            raise FloorError(
                f"floor normal must be a finite non-zero 3-vector, got {self.normal!r}"
            )
        off = float(self.offset)
        if not np.isfinite(off):
            raise FloorError(f"floor offset must be finite, got {self.offset!r}")
        norm = np.linalg.norm(n)
        object.__setattr__(self, "normal", n / norm)
        object.__setattr__(self, "offset", off / norm)

    @classmethod
    def world(cls, up: np.ndarray) -> FloorPlane:
        """The plane through the world origin perpendicular to ``up``.

        This is the world z = 0 plane when ``up`` is +z, as set by
        ``freipose calib --origin-frame``.

        Args:
            up: (3,) up vector.

        Returns:
            The plane with ``source = "world"``.
        """
        return cls(np.asarray(up, dtype=np.float64), 0.0, "world")

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distances (mm, positive above the floor): points (..., 3) -> (...)."""
        return np.asarray(points) @ self.normal - self.offset

    def to_toml(self) -> str:
        """The floor file text (``normal`` and ``offset``, floats written exactly)."""
        n = ", ".join(repr(float(v)) for v in self.normal)
        return (
            "# Floor plane: normal . X = offset (world mm); the normal points up.\n"
            f"normal = [{n}]\noffset = {float(self.offset)!r}\n"
        )


def save_floor(floor: FloorPlane, path: str | Path) -> None:
    """Write a floor TOML file atomically.

    Args:
        floor: the plane.
        path: the floor file.
    """
    atomic_write_text(path, floor.to_toml())


def load_floor(path: str | Path) -> FloorPlane:
    """Read a floor TOML file (``normal = [x, y, z]``, ``offset = mm``).

    Args:
        path: the floor file.

    Returns:
        The plane, with ``source`` the path.

    Raises:
        InputFileError: no such file.
        FloorError: not TOML, an unknown key, or no valid normal and offset.
    """
    path = Path(path)
    data = read_toml(path, "floor file", FloorError)
    check_keys(data, ("normal", "offset"), f"floor file {path}", FloorError)
    if "normal" not in data:
        raise FloorError(
            f"floor file {path}: missing 'normal'; expected normal = [x, y, z] and offset = mm"
        )
    try:
        normal = np.asarray(data["normal"], dtype=np.float64)
        offset = float(data.get("offset", 0.0))
    except (TypeError, ValueError) as exc:
        raise FloorError(f"floor file {path}: normal must be 3 numbers, offset a number") from exc
    return FloorPlane(normal, offset, str(path))


def fit_floor(
    feet: np.ndarray,
    up: np.ndarray,
    cell_mm: float = 50.0,
    quantile: float = 0.1,
    min_points: int = 30,
    iterations: int = 5,
) -> FloorPlane:
    """Fit the floor robustly to the lowest paw positions.

    The paw positions are binned in a grid of ``cell_mm`` cells on the plane perpendicular to
    ``up``; in each cell the points below the cell's ``quantile`` of height are kept (paws in
    stance), so a tilted floor is sampled everywhere the animal walked; the plane is fitted
    to them with outlier rejection (:func:`freipose.geometry.floor.fit_plane_below`).

    Args:
        feet: (..., 3) paw positions (world mm), NaN allowed.
        up: (3,) approximate up vector; the fitted normal points to the same side.
        cell_mm: grid cell size in mm.
        quantile: per cell, the points at most this height quantile are kept.
        min_points: the fewest finite paw positions to fit.
        iterations: rounds of outlier rejection.

    Returns:
        The fitted plane with ``source = "auto"``.
    """
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    pts = np.asarray(feet, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < min_points:
        raise FloorError(
            f"cannot fit the floor: only {len(pts)} finite paw positions (need {min_points}); "
            f"give the floor with --floor FILE or use the world z = 0 plane (--floor world)"
        )
    plane = fit_plane_below(pts, up, cell_mm, quantile, iterations)
    if plane is None:
        raise FloorError("cannot fit the floor: fewer than 3 low paw positions")
    floor = FloorPlane(plane.normal, plane.offset, "auto")
    tilt = np.degrees(np.arccos(np.clip(floor.normal @ up, -1, 1)))
    log.info(
        "fitted floor from %d low paw positions (%d inliers): tilt %.2f deg, offset %.1f mm",
        plane.low_points,
        plane.inliers,
        tilt,
        floor.offset,
    )
    return floor


def resolve_floor(
    spec: str | Path | FloorPlane,
    up: np.ndarray,
    feet: np.ndarray | None = None,
) -> FloorPlane:
    """Turn a ``--floor`` value into a plane.

    Args:
        spec: ``"world"`` (the plane through the world origin perpendicular to ``up``),
            ``"auto"`` (fit to ``feet``), a floor TOML path, or a plane.
        up: (3,) the poses' up vector.
        feet: (..., 3) paw positions for ``"auto"``.

    Returns:
        The plane.

    Raises:
        FloorError: no paws for ``"auto"``, a bad floor file, or a normal far from ``up``.
    """
    if isinstance(spec, FloorPlane):
        return spec
    if str(spec) == "world":
        return FloorPlane.world(up)
    if str(spec) == "auto":
        if feet is None or np.asarray(feet).size == 0:
            raise FloorError(
                "--floor auto needs paw keypoints: the skeleton lists no 'feet'; give the floor "
                "with --floor FILE or use --floor world"
            )
        return fit_floor(feet, up)
    floor = load_floor(spec)
    if floor.normal @ (np.asarray(up) / np.linalg.norm(up)) < 0.5:
        raise FloorError(
            f"floor file {spec}: the normal {floor.normal.round(3).tolist()} is more than 60 deg "
            f"from the poses' up vector {np.round(up, 3).tolist()}; the normal must point up"
        )
    return floor
