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
    stance), so a tilted floor is sampled everywhere the animal walked. A plane
    ``h = a·u + b·v + c`` is then fitted by least squares with iterative rejection of points
    further than 3 robust standard deviations (MAD).

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
    # Orthonormal basis (e1, e2, up).
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(up, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    u, v, h = pts @ e1, pts @ e2, pts @ up
    cu = np.floor(u / cell_mm).astype(np.int64)
    cv = np.floor(v / cell_mm).astype(np.int64)
    _, cell = np.unique(np.stack([cu, cv], axis=1), axis=0, return_inverse=True)
    cell = cell.reshape(-1)
    # Per-cell quantile of the height: sort by (cell, h) and take the rank within the cell.
    order = np.lexsort((h, cell))
    counts = np.bincount(cell)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.empty(len(h), dtype=np.int64)
    rank[order] = np.arange(len(h)) - starts[cell[order]]
    keep = rank <= np.floor(quantile * (counts[cell] - 1))
    u, v, h = u[keep], v[keep], h[keep]
    if len(h) < 3:
        raise FloorError("cannot fit the floor: fewer than 3 low paw positions")
    a = np.stack([u, v, np.ones_like(u)], axis=1)
    inl = np.ones(len(h), dtype=bool)
    coef = np.zeros(3)
    for _ in range(iterations):
        coef, *_ = np.linalg.lstsq(a[inl], h[inl], rcond=None)
        res = h - a @ coef
        mad = 1.4826 * np.median(np.abs(res[inl] - np.median(res[inl])))
        new = np.abs(res) <= max(3.0 * mad, 1e-6)
        if new.sum() < 3 or np.array_equal(new, inl):
            break
        inl = new
    ca, cb, cc = coef
    normal = up - ca * e1 - cb * e2
    s = np.linalg.norm(normal)
    floor = FloorPlane(normal / s, cc / s, "auto")
    tilt = np.degrees(np.arccos(np.clip(floor.normal @ up, -1, 1)))
    log.info(
        "fitted floor from %d low paw positions (%d inliers): tilt %.2f deg, offset %.1f mm",
        len(h),
        int(inl.sum()),
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
