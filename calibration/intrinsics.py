"""Per-camera intrinsics from a selection of board views that covers the image and varies tilt."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from freipose.errors import FreiPoseError
from freipose.geometry.transforms import rodrigues_to_matrix

logger = logging.getLogger(__name__)

__all__ = [
    "DIST_MODELS",
    "CalibrationError",
    "IntrinsicsResult",
    "calibrate_intrinsics",
    "dist_free_mask",
    "select_views",
    "usable_frames",
]

# distortion model name -> which of (k1, k2, p1, p2, k3) are estimated. "auto" estimates
# k1 k2 p1 p2 and the bundle adjustment then drops the tangential terms of a camera where they
# are not significant (see freipose.calibration.pipeline).
DIST_MODELS: dict[str, tuple[bool, bool, bool, bool, bool]] = {
    "auto": (True, True, True, True, False),
    "none": (False, False, False, False, False),
    "k1": (True, False, False, False, False),
    "k1k2": (True, True, False, False, False),
    "k1k2p": (True, True, True, True, False),
    "full": (True, True, True, True, True),
}

MIN_POINTS = 6  # board points a view needs (non-collinear) to constrain a homography
MIN_VIEWS = 4


class CalibrationError(FreiPoseError):
    """Calibration cannot proceed; the message names the camera(s) and what to do."""


def dist_free_mask(model: str) -> np.ndarray:
    """(5,) bool: which distortion coefficients the model estimates."""
    if model not in DIST_MODELS:
        raise CalibrationError(
            f"unknown distortion model {model!r}; expected one of {', '.join(DIST_MODELS)}"
        )
    return np.array(DIST_MODELS[model], dtype=bool)


@dataclass(frozen=True)
class IntrinsicsResult:
    """One camera's intrinsics.

    Attributes:
        K: (3, 3) intrinsic matrix.
        dist: (5,) distortion coefficients.
        rms: RMS reprojection error (px) over the views used.
        frames: (V,) the frame indices of the views used.
        max_tilt_difference_deg: largest tilt difference between two of the views (degrees).
        coverage: fraction of the image the views' boards cover.
    """

    K: np.ndarray
    dist: np.ndarray
    rms: float
    frames: np.ndarray
    max_tilt_difference_deg: float
    coverage: float


def _non_degenerate(obj: np.ndarray) -> bool:
    """Whether planar board points span 2D (not all on one line)."""
    c = obj[:, :2] - obj[:, :2].mean(axis=0)
    s = np.linalg.svd(c, compute_uv=False)
    return len(s) == 2 and s[1] > 1e-6 * max(s[0], 1e-12)


def usable_frames(
    points: np.ndarray, object_points: np.ndarray, min_points: int = MIN_POINTS
) -> np.ndarray:
    """The frames with enough detected points that are not all on one line.

    Args:
        points: (F, P, 2) detections (NaN = missing).
        object_points: (P, 3) board points.
        min_points: detected points a frame needs.

    Returns:
        (F,) bool.
    """
    mask = np.isfinite(points[..., 0])
    ok = mask.sum(axis=1) >= min_points
    for f in np.flatnonzero(ok):
        if not _non_degenerate(object_points[mask[f]]):
            ok[f] = False
    return ok


def _hull_cells(pts: np.ndarray, size: tuple[int, int], grid: tuple[int, int]) -> np.ndarray:
    """(gy, gx) bool: coverage cells inside the convex hull of ``pts``."""
    import cv2

    w, h = size
    gx, gy = grid
    img = np.zeros((gy, gx), np.uint8)
    hull = cv2.convexHull(np.asarray(pts, np.float32).reshape(-1, 1, 2))
    scaled = hull.reshape(-1, 2) * np.array([gx / w, gy / h])
    cv2.fillConvexPoly(img, np.round(scaled).astype(np.int32), 1)
    return img.astype(bool)


def select_views(
    points: np.ndarray,
    object_points: np.ndarray,
    size: tuple[int, int],
    max_views: int = 40,
    grid: tuple[int, int] = (16, 12),
) -> tuple[np.ndarray, float, float]:
    """Greedy choice of views that cover the image and vary the board tilt (after FreiCalib).

    Views are taken in order of detected points; one is added if its board normal differs by
    more than 10 degrees from every chosen view or it adds more than 5 % new image coverage.

    Args:
        points: (F, P, 2) detections (NaN = missing).
        object_points: (P, 3) board points.
        size: image (width, height).
        max_views: most views to choose.
        grid: (columns, rows) of the coverage cells.

    Returns:
        ``(frames (V,) int, coverage fraction, max tilt difference in degrees)``.
    """
    import cv2

    ok = usable_frames(points, object_points)
    cand = np.flatnonzero(ok)
    if len(cand) == 0:
        return cand, 0.0, 0.0
    mask = np.isfinite(points[..., 0])
    w, h = size
    f_guess = 0.86 * w
    K = np.array([[f_guess, 0, (w - 1) / 2], [0, f_guess, (h - 1) / 2], [0, 0, 1.0]])
    normals: dict[int, np.ndarray] = {}
    for fc in cand:
        m = mask[fc]
        okp, rvec, _t = cv2.solvePnP(
            object_points[m].astype(np.float64),
            points[fc, m].astype(np.float64),
            K,
            None,
            flags=cv2.SOLVEPNP_IPPE,
        )
        if okp:
            normals[int(fc)] = rodrigues_to_matrix(rvec)[:, 2]
    order = sorted(normals, key=lambda f: -int(mask[f].sum()))
    chosen: list[int] = []
    covered = np.zeros((grid[1], grid[0]), bool)
    max_diff = 0.0
    for f in order:
        if len(chosen) >= max_views:
            break
        cells = _hull_cells(points[f, mask[f]], size, grid)
        new_cov = (cells & ~covered).sum() / covered.size
        if chosen:
            dots = np.clip([abs(normals[f] @ normals[g]) for g in chosen], -1, 1)
            min_angle = np.degrees(np.arccos(np.max(dots)))
        else:
            min_angle = 180.0
        if min_angle > 10.0 or new_cov > 0.05:
            for g in chosen:
                d = np.degrees(np.arccos(np.clip(abs(normals[f] @ normals[g]), -1, 1)))
                max_diff = max(max_diff, float(d))
            chosen.append(int(f))
            covered |= cells
    # top up with the best remaining views so that the estimate is well averaged
    if len(chosen) < min(max_views, 12):
        for f in order:
            if len(chosen) >= min(max_views, 12):
                break
            if f not in chosen:
                chosen.append(int(f))
                covered |= _hull_cells(points[f, mask[f]], size, grid)
    return np.array(sorted(chosen), dtype=np.int64), float(covered.mean()), max_diff


def calibrate_intrinsics(
    points: np.ndarray,
    object_points: np.ndarray,
    size: tuple[int, int],
    dist_model: str = "k1k2p",
    camera: str = "camera",
    max_views: int = 40,
    fix_principal_point: bool = False,
) -> IntrinsicsResult:
    """Intrinsics of one camera with ``cv2.calibrateCamera`` on a selection of views.

    Args:
        points: (F, P, 2) detections, NaN = missing.
        object_points: (P, 3) board points (mm).
        size: (width, height).
        dist_model: one of :data:`DIST_MODELS`.
        camera: name for messages.
        max_views: most views to use.
        fix_principal_point: keep the principal point at the image centre
            ``((w - 1) / 2, (h - 1) / 2)``.

    Raises:
        CalibrationError: fewer than 4 usable views.
    """
    import cv2

    free = dist_free_mask(dist_model)
    frames, coverage, tilt = select_views(points, object_points, size, max_views=max_views)
    n_usable = int(usable_frames(points, object_points).sum())
    if len(frames) < MIN_VIEWS:
        raise CalibrationError(
            f"camera {camera}: only {n_usable} frame(s) show the board with at least "
            f"{MIN_POINTS} corners; intrinsics need at least {MIN_VIEWS} such frames at different "
            f"tilts. Record more frames with the whole board visible, or pass --fix-intrinsics "
            f"with known intrinsics"
        )
    if tilt < 10.0:
        logger.warning(
            "camera %s: the chosen board views differ in tilt by only %.1f degrees; the focal "
            "length is poorly constrained (tilt the board more)",
            camera,
            tilt,
        )
    mask = np.isfinite(points[..., 0])
    obj = [object_points[mask[f]].astype(np.float32) for f in frames]
    img = [points[f, mask[f]].astype(np.float32).reshape(-1, 1, 2) for f in frames]
    w, h = size
    K0 = cv2.initCameraMatrix2D(obj, img, (w, h), 1.0)
    if not np.all(np.isfinite(K0)) or K0[0, 0] <= 0:
        K0 = np.array([[0.86 * w, 0, (w - 1) / 2], [0, 0.86 * w, (h - 1) / 2], [0, 0, 1.0]])
    flags = cv2.CALIB_USE_INTRINSIC_GUESS
    if fix_principal_point:
        K0[0, 2], K0[1, 2] = (w - 1) / 2, (h - 1) / 2
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
    for i, fl in zip((0, 1, 4), (cv2.CALIB_FIX_K1, cv2.CALIB_FIX_K2, cv2.CALIB_FIX_K3)):
        if not free[i]:
            flags |= fl
    if not free[2] and not free[3]:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    rms, K, dist, _r, _t = cv2.calibrateCamera(
        obj, img, (w, h), K0.astype(np.float64), np.zeros(5), flags=flags, criteria=crit
    )
    dist = np.asarray(dist, np.float64).reshape(-1)[:5]
    dist = np.where(free, dist, 0.0)
    return IntrinsicsResult(
        K=np.asarray(K, np.float64),
        dist=dist,
        rms=float(rms),
        frames=frames,
        max_tilt_difference_deg=tilt,
        coverage=coverage,
    )
