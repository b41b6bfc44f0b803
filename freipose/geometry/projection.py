"""Vectorized NumPy projection, undistortion and rays of ``Camera`` objects.

Conventions: see the package docstring. All functions broadcast over leading axes. Points
behind a camera (depth <= 0) project to NaN; NaN inputs give NaN outputs. The array-level
pinhole model is :mod:`freipose.geometry.pinhole`, the lens distortion
:mod:`freipose.geometry.distortion`.
"""

from __future__ import annotations

import numpy as np

from freipose.geometry._checks import check_last
from freipose.geometry.camera import Camera, CameraRig
from freipose.geometry.distortion import undistort_normalized
from freipose.geometry.pinhole import apply_intrinsics, project_points, remove_intrinsics

__all__ = ["pixel_to_ray", "project", "project_rig", "undistort_pixels", "world_to_camera"]


def world_to_camera(points: np.ndarray, camera: Camera) -> np.ndarray:
    """World points to camera coordinates.

    Args:
        points: (..., 3) world points in mm.
        camera: the camera.

    Returns:
        (..., 3) points in the camera's frame in mm.
    """
    X = check_last(points, 3, "points")
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
    dist = camera.dist if distort and camera.has_distortion else None
    return project_points(points, camera.K, camera.R, camera.t, dist)


def project_rig(points: np.ndarray, rig: CameraRig, distort: bool = True) -> np.ndarray:
    """Project world points into every camera of a rig (same as ``rig.project``).

    Args:
        points: (..., P, 3) world points in mm.
        rig: the cameras.
        distort: apply the lens distortion (True) or the pure pinhole model (False).

    Returns:
        (..., C, P, 2) pixel coordinates.
    """
    return rig.project(points, distort=distort)


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
