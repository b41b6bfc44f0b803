"""Vectorized NumPy projection, distortion, undistortion and rays (conventions: package doc).

All functions broadcast over leading axes. Points behind a camera (depth <= 0) project
to NaN; NaN inputs give NaN outputs.
"""

from __future__ import annotations

import numpy as np

from freipose.geometry.camera import Camera, CameraRig

_EPS_DEPTH = 1e-9


def _check_last(arr: np.ndarray, n: int, what: str) -> np.ndarray:
    a = np.asarray(arr, dtype=np.float64)
    if a.ndim == 0 or a.shape[-1] != n:
        raise ValueError(f"{what} must have shape (..., {n}), got shape {a.shape}")
    return a


def distort_normalized(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Apply OpenCV distortion to normalized coordinates.

    Args:
        xy: (..., 2) normalized image coordinates (x/z, y/z).
        dist: (5,) coefficients ``(k1, k2, p1, p2, k3)``.

    Returns:
        (..., 2) distorted normalized coordinates.
    """
    xy = _check_last(xy, 2, "xy")
    k1, k2, p1, p2, k3 = np.asarray(dist, dtype=np.float64).reshape(5)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def _distortion_jacobian(xy: np.ndarray, d: np.ndarray) -> np.ndarray:
    """d(distorted)/d(xy), (..., 2, 2); ``d`` is (5,)."""
    k1, k2, p1, p2, k3 = d
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial_dr2 = k1 + 2 * k2 * r2 + 3 * k3 * r2 * r2
    drx, dry = dradial_dr2 * 2 * x, dradial_dr2 * 2 * y
    J = np.empty(xy.shape[:-1] + (2, 2))
    J[..., 0, 0] = radial + x * drx + 2 * p1 * y + 6 * p2 * x
    J[..., 0, 1] = x * dry + 2 * p1 * x + 2 * p2 * y
    J[..., 1, 0] = y * drx + 2 * p1 * x + 2 * p2 * y
    J[..., 1, 1] = radial + y * dry + 6 * p1 * y + 2 * p2 * x
    return J


def undistort_normalized(xy_d: np.ndarray, dist: np.ndarray, iterations: int = 20) -> np.ndarray:
    """Invert OpenCV distortion for normalized coordinates (fixed point, then Newton).

    Args:
        xy_d: (..., 2) distorted normalized coordinates.
        dist: (5,) coefficients.
        iterations: fixed-point iterations before the Newton polish.

    Returns:
        (..., 2) undistorted normalized coordinates.
    """
    xy_d = _check_last(xy_d, 2, "xy_d")
    d = np.asarray(dist, dtype=np.float64).reshape(5)
    if not np.any(d):
        return xy_d.copy()
    k1, k2, p1, p2, k3 = d
    xy = xy_d.copy()
    for _ in range(iterations):  # OpenCV's scheme: a good start for Newton
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        xy = np.stack([(xy_d[..., 0] - dx) / radial, (xy_d[..., 1] - dy) / radial], axis=-1)
    for _ in range(4):  # Newton polish to machine precision
        res = distort_normalized(xy, d) - xy_d
        J = _distortion_jacobian(xy, d)
        det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            sx = (J[..., 1, 1] * res[..., 0] - J[..., 0, 1] * res[..., 1]) / det
            sy = (-J[..., 1, 0] * res[..., 0] + J[..., 0, 0] * res[..., 1]) / det
        xy = xy - np.stack([sx, sy], axis=-1)
    return xy


def apply_intrinsics(xy: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Normalized (..., 2) to pixels (..., 2) with K (3, 3), skew included."""
    xy = _check_last(xy, 2, "xy")
    K = np.asarray(K, dtype=np.float64)
    u = K[..., 0, 0, None] * xy[..., 0:1] + K[..., 0, 1, None] * xy[..., 1:2] + K[..., 0, 2, None]
    v = K[..., 1, 1, None] * xy[..., 1:2] + K[..., 1, 2, None]
    return np.concatenate([u, v], axis=-1)


def remove_intrinsics(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixels (..., 2) to normalized (distorted) coordinates (..., 2), skew included."""
    uv = _check_last(uv, 2, "uv")
    K = np.asarray(K, dtype=np.float64)
    y = (uv[..., 1] - K[1, 2]) / K[1, 1]
    x = (uv[..., 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return np.stack([x, y], axis=-1)


def world_to_camera(points: np.ndarray, camera: Camera) -> np.ndarray:
    """World points (..., 3) to camera coordinates (..., 3) in mm."""
    X = _check_last(points, 3, "points")
    return X @ camera.R.T + camera.t


def project(points: np.ndarray, camera: Camera, distort: bool = True) -> np.ndarray:
    """Project world points into one camera.

    Args:
        points: (..., 3) world points in mm (NaN allowed).
        camera: the camera.
        distort: apply the lens distortion (True) or the pure pinhole model (False).

    Returns:
        (..., 2) pixel coordinates; NaN for NaN input or points with depth <= 0.
    """
    Xc = world_to_camera(points, camera)
    z = Xc[..., 2:3]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = np.where(z > _EPS_DEPTH, Xc[..., :2] / z, np.nan)
    if distort and camera.has_distortion:
        xy = distort_normalized(xy, camera.dist)
    return apply_intrinsics(xy, camera.K)


def project_rig(points: np.ndarray, rig: CameraRig, distort: bool = True) -> np.ndarray:
    """Project world points (..., P, 3) into every camera of ``rig``: (..., C, P, 2)."""
    X = _check_last(points, 3, "points")
    if X.ndim < 2:
        raise ValueError(f"points must have shape (..., P, 3), got shape {X.shape}")
    return np.stack([project(X, c, distort) for c in rig], axis=-3)


def undistort_pixels(uv: np.ndarray, camera: Camera, to_pixels: bool = False) -> np.ndarray:
    """Remove lens distortion from pixel coordinates.

    Args:
        uv: (..., 2) observed (distorted) pixels.
        camera: the camera that observed them.
        to_pixels: if True, return ideal pinhole pixels (``K`` applied again) instead of
            normalized coordinates.

    Returns:
        (..., 2) undistorted normalized coordinates (or ideal pixels).
    """
    xy = undistort_normalized(remove_intrinsics(uv, camera.K), camera.dist)
    return apply_intrinsics(xy, camera.K) if to_pixels else xy


def pixel_to_ray(uv: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """World rays through pixels.

    Args:
        uv: (..., 2) pixel coordinates.
        camera: the camera.

    Returns:
        ``(origin, direction)``: origin (3,) the camera centre in mm, direction (..., 3)
        unit vectors in world coordinates.
    """
    xy = undistort_pixels(uv, camera)
    d = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1) @ camera.R  # R.T @ d
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return camera.center, d
