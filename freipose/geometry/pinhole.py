"""The pinhole camera on plain arrays: intrinsics and the projection of world points.

These functions take the camera's parameters as arrays (``K``, ``R``, ``t``, ``dist``), so
that :mod:`freipose.geometry.camera` and :mod:`freipose.geometry.projection` (which takes
``Camera`` objects) can both use them without importing each other.
"""

from __future__ import annotations

import numpy as np

from freipose.geometry._checks import check_last
from freipose.geometry.distortion import distort_normalized

__all__ = ["apply_intrinsics", "project_points", "remove_intrinsics"]

# Points at or below this depth (mm) in front of the camera project to NaN.
_EPS_DEPTH = 1e-9


def apply_intrinsics(xy: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Normalized coordinates to pixels, skew included.

    Args:
        xy: (..., 2) normalized (distorted) coordinates.
        K: (3, 3) intrinsic matrix (or (..., 3, 3) broadcastable to ``xy``).

    Returns:
        (..., 2) pixels.
    """
    xy = check_last(xy, 2, "xy")
    K = np.asarray(K, dtype=np.float64)
    u = K[..., 0, 0, None] * xy[..., 0:1] + K[..., 0, 1, None] * xy[..., 1:2] + K[..., 0, 2, None]
    v = K[..., 1, 1, None] * xy[..., 1:2] + K[..., 1, 2, None]
    return np.concatenate([u, v], axis=-1)


def remove_intrinsics(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixels to normalized (still distorted) coordinates, skew included.

    Args:
        uv: (..., 2) pixels.
        K: (3, 3) intrinsic matrix, or (..., 3, 3) broadcastable to ``uv[..., 0]``.

    Returns:
        (..., 2) normalized coordinates.
    """
    uv = check_last(uv, 2, "uv")
    K = np.asarray(K, dtype=np.float64)
    y = (uv[..., 1] - K[..., 1, 2]) / K[..., 1, 1]
    x = (uv[..., 0] - K[..., 0, 2] - K[..., 0, 1] * y) / K[..., 0, 0]
    return np.stack([x, y], axis=-1)


def project_points(
    points: np.ndarray,
    K: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    dist: np.ndarray | None = None,
) -> np.ndarray:
    """Project world points into one camera, or into a stack of C cameras at once.

    Args:
        points: (..., 3) world points in mm (NaN allowed); for C cameras (..., 1, P, 3).
        K: (3, 3) intrinsic matrix; for C cameras (C, 1, 3, 3).
        R: (3, 3) world→camera rotation; for C cameras (C, 3, 3).
        t: (3,) world→camera translation in mm; for C cameras (C, 1, 3).
        dist: (5,) distortion coefficients (for C cameras (C, 1, 5)), or None for the pure
            pinhole model.

    Returns:
        (..., 2) pixel coordinates (for C cameras (..., C, P, 2)); NaN for NaN input or
        points with depth <= 0.
    """
    X = check_last(points, 3, "points")
    Xc = X @ np.swapaxes(R, -1, -2) + t
    z = Xc[..., 2:3]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = np.where(z > _EPS_DEPTH, Xc[..., :2] / z, np.nan)
    if dist is not None:
        xy = distort_normalized(xy, dist)
    return apply_intrinsics(xy, K)
