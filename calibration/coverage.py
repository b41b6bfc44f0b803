"""Where the board went: per camera, the image regions and depths it covered, and the floor.

A lens model is fitted where the board was seen and extrapolated elsewhere. Where the
animal is (on the floor) but the board never was, distances can be off by percent while
the board itself measures right. :func:`board_coverage` gives, per camera, the image cells
with detected corners, the range of the board's distances from the camera and, when the
floor is known (``--origin-frame``: the board on the floor), how many of the camera's board
views came near the floor and how much of the floor's image region (the floor that two
cameras see, under where the board went) holds detected corners;
:func:`coverage_warnings` turns a floor that was not covered into a warning.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from freipose.calibration.detect import CameraDetections
from freipose.geometry import CameraRig, project
from freipose.geometry.floor import orthonormal_basis
from freipose.io.calibration_world import WorldUp

__all__ = [
    "FLOOR_NEAR_MM",
    "MIN_FLOOR_REGION",
    "MIN_FLOOR_VIEWS",
    "CameraCoverage",
    "board_coverage",
    "coverage_warnings",
    "floor_grid",
]

GRID = (8, 6)  # image cells (columns, rows) of the coverage grid
FLOOR_NEAR_MM = 50.0  # a board view within this height of the floor covers the floor
MIN_FLOOR_VIEWS = 3  # fewer near-floor views than this: the floor was not covered
MIN_FLOOR_REGION = 0.5  # the least share of the floor's image region with corners


@dataclass(frozen=True, eq=False)
class CameraCoverage:
    """What the board covered in one camera.

    Attributes:
        name: the camera.
        grid: (rows, columns) detected corners per image cell (``GRID``).
        image_fraction: the share of the cells with at least one detected corner.
        depth_mm: (5th percentile, median, 95th percentile) of the detected corners'
            distance along the optical axis (mm), None without board poses.
        floor_views: board views of this camera with a corner within ``FLOOR_NEAR_MM``
            of the floor (None: floor unknown).
        lowest_mm: the lowest detected corner's height above the floor (None: unknown).
        floor_region: the share of the floor's image region (the points of
            :func:`floor_grid` this camera sees) lying in cells with corners (None: floor
            unknown or not in view).
        floor_pixels: (M, 2) pixels of the floor region in this camera (None: unknown).
    """

    name: str
    grid: np.ndarray
    image_fraction: float
    depth_mm: tuple[float, float, float] | None
    floor_views: int | None = None
    lowest_mm: float | None = None
    floor_region: float | None = None
    floor_pixels: np.ndarray | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible summary (for ``summary.json``)."""

        def r(x: float | None) -> float | None:
            return None if x is None else round(float(x), 3)

        return {
            "grid_columns_rows": list(GRID),
            "image_cells_covered": round(self.image_fraction, 3),
            "depth_mm_p5_median_p95": None
            if self.depth_mm is None
            else [round(float(x), 1) for x in self.depth_mm],
            "floor_views": self.floor_views,
            "lowest_above_floor_mm": r(self.lowest_mm),
            "floor_region_covered": r(self.floor_region),
        }


def _grid(det: CameraDetections) -> np.ndarray:
    """(rows, columns) detected corners per image cell."""
    w, h = det.size
    pts = det.points[det.mask]
    H, _xe, _ye = np.histogram2d(
        pts[:, 0], pts[:, 1], bins=GRID, range=[[-0.5, w - 0.5], [-0.5, h - 0.5]]
    )
    return H.T.astype(np.int64)


def _cells(det: CameraDetections, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The (row, column) grid cell of each (N, 2) pixel (clipped to the image)."""
    w, h = det.size
    col = np.clip(((uv[:, 0] + 0.5) / w * GRID[0]).astype(np.int64), 0, GRID[0] - 1)
    row = np.clip(((uv[:, 1] + 0.5) / h * GRID[1]).astype(np.int64), 0, GRID[1] - 1)
    return row, col


def _world_corners(
    det: CameraDetections, board_poses: np.ndarray, obj: np.ndarray
) -> list[np.ndarray]:
    """Per frame with a board pose, the (n, 3) world points of the corners ``det`` detected."""
    out = []
    for f in np.flatnonzero(det.mask.any(axis=1)):
        B = board_poses[f]
        if np.isfinite(B[0, 0]):
            out.append(obj[det.mask[f]] @ B[:3, :3].T + B[:3, 3])
    return out


def _in_view(cam: Any, size: tuple[int, int], X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) pixels of world points ``X`` (N, 3) and whether each is in the camera's image.

    The pinhole image must be near the view too (distortion can fold far points into it).
    """
    w, h = size
    uv = project(X, cam)
    pin = project(X, cam, distort=False)
    seen = (
        np.isfinite(uv).all(axis=1)
        & np.isfinite(pin).all(axis=1)
        & (np.abs(pin[:, 0] - w / 2) < 0.75 * w)
        & (np.abs(pin[:, 1] - h / 2) < 0.75 * h)
        & (uv[:, 0] >= 0)
        & (uv[:, 0] <= w - 1)
        & (uv[:, 1] >= 0)
        & (uv[:, 1] <= h - 1)
    )
    return uv, seen


def floor_grid(
    rig: CameraRig, up: np.ndarray, floor: float, board_points: np.ndarray, n: int = 40
) -> np.ndarray:
    """(M, 3) points of the floor that at least two cameras see: where an animal is measured.

    The floor is sampled over the horizontal extent of the board's points (where the board
    went: the arena, when it was waved all over it) and kept where two cameras see it. The
    cameras' positions do not widen it: cameras standing around a small arena see floor
    outside its walls, where neither the animal nor the board goes.

    Args:
        rig: the calibrated cameras.
        up: (3,) unit up vector.
        floor: the floor's height along ``up`` (mm).
        board_points: (N, 3) detected board points in the world (mm).
        n: samples along each side.
    """
    e1, e2 = orthonormal_basis(up)
    a, b = board_points @ e1, board_points @ e2
    s, t = np.meshgrid(np.linspace(a.min(), a.max(), n), np.linspace(b.min(), b.max(), n))
    X = s.reshape(-1, 1) * e1 + t.reshape(-1, 1) * e2 + floor * up
    views = sum(_in_view(cam, cam.size, X)[1].astype(int) for cam in rig)
    return X[np.asarray(views) >= 2]


def board_coverage(
    dets: Sequence[CameraDetections],
    rig: CameraRig,
    board_poses: np.ndarray,
    object_points: np.ndarray,
    up: WorldUp | None,
) -> tuple[CameraCoverage, ...]:
    """Per camera, the image cells, depths and floor the board covered.

    Args:
        dets: per camera, the detections (rig order).
        rig: the calibrated cameras (world frame).
        board_poses: (F, 4, 4) board→world per frame, NaN where unknown.
        object_points: (P, 3) the board's points (board frame, mm).
        up: the world's up direction; the floor parts need its ``floor``.

    Returns:
        One coverage per camera.
    """
    floor = None if up is None else up.floor
    every = [p for d in dets for p in _world_corners(d, board_poses, object_points)]
    region = None
    if up is not None and floor is not None and every:
        region = floor_grid(rig, up.up, floor, np.concatenate(every))
    out = []
    for d, cam in zip(dets, rig):
        grid = _grid(d)
        frames = _world_corners(d, board_poses, object_points)
        depth = None
        if frames:
            z = (np.concatenate(frames) @ cam.R.T + cam.t)[:, 2]
            p5, p50, p95 = np.percentile(z, [5, 50, 95])
            depth = (float(p5), float(p50), float(p95))
        cov = CameraCoverage(d.name, grid, float(np.mean(grid > 0)), depth)
        if up is not None and floor is not None and region is not None and frames:
            lows = np.array([float(np.min(p @ up.up)) - floor for p in frames])
            uv, seen = _in_view(cam, d.size, region)
            share = None
            if seen.any():
                row, col = _cells(d, uv[seen])
                share = float(np.mean(grid[row, col] > 0))
            cov = CameraCoverage(
                d.name, grid, cov.image_fraction, depth, int(np.sum(lows <= FLOOR_NEAR_MM)),
                float(lows.min()), share, uv[seen],
            )  # fmt: skip
        out.append(cov)
    return tuple(out)


def coverage_warnings(coverage: Sequence[CameraCoverage]) -> list[str]:
    """A warning per camera whose board views did not cover the floor (floor known)."""
    out = []
    for c in coverage:
        if c.floor_views is None:
            continue
        few = c.floor_views < MIN_FLOOR_VIEWS
        region = c.floor_region is not None and c.floor_region < MIN_FLOOR_REGION
        if not (few or region):
            continue
        parts = []
        if few:
            parts.append(
                f"the board came within {FLOOR_NEAR_MM:.0f} mm of the floor in {c.floor_views} "
                f"of its views (lowest corner {c.lowest_mm:.0f} mm above the floor)"
            )
        if region and c.floor_region is not None:
            parts.append(
                f"only {100 * c.floor_region:.0f} % of the floor's image region holds detected "
                f"corners"
            )
        out.append(
            f"camera {c.name}: {' and '.join(parts)}: distances near the floor, where the "
            f"animal is, rest on the lens model's extrapolation and can be off by percent; "
            f"record the board low and flat near the floor as well, all over the arena "
            f"(the report's coverage_{c.name}.png shows where it was)"
        )
    return out
