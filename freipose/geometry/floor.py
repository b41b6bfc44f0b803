"""The plane an animal rests on, and the world's up direction estimated from 3D points.

A floor is the plane ``{X : normal · X = offset}`` with a unit ``normal`` pointing up; the
height of a point above it is ``normal · X - offset`` (mm). :func:`fit_plane_below` fits
that plane to the lowest of many points (paws in stance) given an approximate up;
:func:`estimate_up` finds the up direction itself from points of an animal moving over
the floor, seen by cameras most of which are above it, and says how well the points
determine it (:func:`up_uncertainty`: the spread of the estimate over resampled instants).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "LowPlane",
    "UpEstimate",
    "estimate_up",
    "fit_plane_below",
    "orthonormal_basis",
    "up_uncertainty",
]


@dataclass(frozen=True, eq=False)
class LowPlane:
    """A plane fitted to the lowest points.

    Attributes:
        normal: (3,) unit normal, on the same side as the given up.
        offset: the plane is ``normal · X = offset`` (mm).
        low_points: points kept as the lowest of their grid cell.
        inliers: low points within 3 robust standard deviations of the plane.
    """

    normal: np.ndarray
    offset: float
    low_points: int
    inliers: int


def orthonormal_basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two (3,) unit vectors that complete the unit ``up`` to a right-handed basis."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(up, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1)


def fit_plane_below(
    points: np.ndarray,
    up: np.ndarray,
    cell_mm: float = 50.0,
    quantile: float = 0.1,
    iterations: int = 5,
) -> LowPlane | None:
    """Fit a plane robustly to the lowest points.

    The points are binned in a grid of ``cell_mm`` cells on the plane perpendicular to
    ``up``; in each cell the points below the cell's ``quantile`` of height are kept, so a
    tilted floor is sampled everywhere the points went. A plane ``h = a·u + b·v + c`` is
    then fitted by least squares with iterative rejection of points further than 3 robust
    standard deviations (MAD).

    Args:
        points: (..., 3) points (mm), NaN allowed.
        up: (3,) approximate up vector; the fitted normal points to the same side.
        cell_mm: grid cell size in mm.
        quantile: per cell, the points at most this height quantile are kept.
        iterations: rounds of outlier rejection.

    Returns:
        The plane, or None when fewer than 3 low points remain.
    """
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    e1, e2 = orthonormal_basis(up)
    u, v, h = pts @ e1, pts @ e2, pts @ up
    cu = np.floor(u / cell_mm).astype(np.int64)
    cv = np.floor(v / cell_mm).astype(np.int64)
    if len(h) == 0:
        return None
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
        return None
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
    return LowPlane(normal / s, float(cc / s), int(len(h)), int(inl.sum()))


@dataclass(frozen=True, eq=False)
class UpEstimate:
    """The up direction estimated from points.

    Attributes:
        up: (3,) unit up vector (world frame).
        floor: the floor's offset along ``up`` (mm): ``up · X = floor`` on the floor.
        flatness: the smallest over the middle eigenvalue of the points' scatter (0 for
            points spread over a plane; near 1 when the thin direction is not determined).
        cameras_above: how many of the cameras are above the floor.
        points: the finite points used.
        instants: the instants (first axis of the points) with a finite point.
        uncertainty_deg: the 95th percentile of the angle between ``up`` and the estimates
            from resampled instants (:func:`up_uncertainty`), degrees.
    """

    up: np.ndarray
    floor: float
    flatness: float
    cameras_above: int
    points: int
    instants: int = 0
    uncertainty_deg: float = float("nan")


def _by_instant(points: np.ndarray) -> np.ndarray:
    """(T, P, 3) points per instant: the first axis is time; (N, 3): one point an instant."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim <= 2:
        return pts.reshape(-1, 1, 3)
    return pts.reshape(len(pts), -1, 3)


def _finite(points: np.ndarray) -> np.ndarray:
    pts = points.reshape(-1, 3)
    return pts[np.isfinite(pts).all(axis=1)]


def _up_and_floor(pts: np.ndarray, centers: np.ndarray) -> tuple[np.ndarray, float, float]:
    """(up, floor, flatness) of finite (N, 3) points: least scatter, sided, plane-refined."""
    centred = pts - pts.mean(axis=0)
    evals, evecs = np.linalg.eigh(centred.T @ centred / len(pts))
    up = evecs[:, 0]
    side = (centers - np.median(pts, axis=0)) @ up
    if np.sum(side > 0) < np.sum(side < 0) or (
        np.sum(side > 0) == np.sum(side < 0) and side.sum() < 0
    ):
        up = -up
    plane = fit_plane_below(pts, up)
    if plane is not None:
        up, floor = plane.normal, plane.offset
    else:
        floor = float(np.min(pts @ up))
    return up, float(floor), float(evals[0] / max(evals[1], 1e-12))


def up_uncertainty(
    points: np.ndarray,
    camera_centers: np.ndarray,
    up: np.ndarray,
    resamples: int = 64,
    blocks: int = 20,
    max_instants: int = 2000,
) -> float:
    """How well the points determine the up: the spread of re-estimates over instants.

    The instants (first axis) are cut into at most ``blocks`` runs of consecutive instants
    (consecutive video frames are not independent evidence), the runs are drawn with
    replacement ``resamples`` times and the up is estimated from each draw as
    :func:`estimate_up` does. Deterministic (a fixed generator).

    Args:
        points: (T, ..., 3) points over time (mm), NaN allowed.
        camera_centers: (C, 3) camera centres in the same frame.
        up: (3,) the estimate from all the points.
        resamples: the number of draws.
        blocks: the most runs the instants are cut into.
        max_instants: longer recordings are thinned to this many evenly spaced instants.

    Returns:
        The 95th percentile of the angle between ``up`` and the re-estimates (degrees);
        180 when a draw has too few points to estimate anything.
    """
    per = _by_instant(points)
    if len(per) > max_instants:
        per = per[np.linspace(0, len(per) - 1, max_instants).round().astype(np.int64)]
    runs = np.array_split(np.arange(len(per)), min(blocks, len(per)))
    centers = np.asarray(camera_centers, dtype=np.float64).reshape(-1, 3)
    rng = np.random.default_rng(0)
    angles = np.empty(resamples)
    for b in range(resamples):
        pick = np.concatenate([runs[i] for i in rng.integers(0, len(runs), len(runs))])
        pts = _finite(per[pick])
        if len(pts) < 10:
            angles[b] = 180.0
            continue
        u, _, _ = _up_and_floor(pts, centers)
        angles[b] = np.degrees(np.arccos(np.clip(float(u @ up), -1.0, 1.0)))
    return float(np.percentile(angles, 95))


def estimate_up(
    points: np.ndarray, camera_centers: np.ndarray, uncertainty: bool = True
) -> UpEstimate | None:
    """Estimate the up direction from points of an animal moving over a floor.

    The animal's points over time spread along the floor more than across it, so the
    direction of least scatter is the floor's normal up to its sign; the sign puts most
    camera centres above the floor (a rig may have a camera below a transparent floor, not
    most of them). The normal is then refined by :func:`fit_plane_below` on the lowest
    points, which also gives the floor's height. A few instants, or an animal that walked
    along one line or reared a lot, leave the direction poorly determined: its
    :func:`up_uncertainty` says by how much.

    Args:
        points: (T, ..., 3) points over time (mm), NaN allowed; the first axis is time
            (a (N, 3) array: every point its own instant).
        camera_centers: (C, 3) camera centres in the same frame.
        uncertainty: also measure the uncertainty (else ``uncertainty_deg`` is NaN).

    Returns:
        The estimate, or None for fewer than 10 finite points.
    """
    per = _by_instant(points)
    pts = _finite(per)
    if len(pts) < 10:
        return None
    centers = np.asarray(camera_centers, dtype=np.float64).reshape(-1, 3)
    up, floor, flat = _up_and_floor(pts, centers)
    above = int(np.sum(centers @ up - floor > 0))
    instants = int(np.isfinite(per).all(axis=2).any(axis=1).sum())
    spread = up_uncertainty(per, centers, up) if uncertainty else float("nan")
    return UpEstimate(up, floor, flat, above, len(pts), instants, spread)
