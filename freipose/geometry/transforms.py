"""Rotation vectors and 4x4 rigid transforms (conventions: see the package docstring).

A rotation vector (Rodrigues vector) ``r`` (3,) is the rotation axis scaled by the angle
in radians. A rigid transform ``T`` (4, 4) maps homogeneous points ``X' = T @ X``; its
upper-left (3, 3) block is the rotation ``R`` and its last column the translation ``t``.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = [
    "invert_transform",
    "matrix_to_rodrigues",
    "rodrigues",
    "rodrigues_to_matrix",
    "transform",
]

# Below this angle (radians) :func:`rodrigues` uses the first-order rotation ``I + [r]x``.
_SMALL_ANGLE = 1e-12


def rodrigues_to_matrix(rvec: np.ndarray) -> np.ndarray:
    """Rotation matrix of one rotation vector, computed by OpenCV.

    Args:
        rvec: (3,) rotation vector (any shape with 3 elements).

    Returns:
        (3, 3) rotation matrix.
    """
    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
    return np.asarray(R)


def matrix_to_rodrigues(R: np.ndarray) -> np.ndarray:
    """Rotation vector of one rotation matrix, computed by OpenCV.

    Args:
        R: (3, 3) rotation matrix.

    Returns:
        (3,) rotation vector.
    """
    rvec, _ = cv2.Rodrigues(np.asarray(R, dtype=np.float64))
    return np.asarray(rvec).reshape(3)


def _cross_matrix(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``[v]x`` (..., 3, 3) of vectors ``v`` (..., 3)."""
    M = np.zeros(v.shape[:-1] + (3, 3))
    M[..., 0, 1], M[..., 0, 2] = -v[..., 2], v[..., 1]
    M[..., 1, 0], M[..., 1, 2] = v[..., 2], -v[..., 0]
    M[..., 2, 0], M[..., 2, 1] = -v[..., 1], v[..., 0]
    return M


def rodrigues(r: np.ndarray) -> np.ndarray:
    """Rotation matrices of many rotation vectors (vectorized Rodrigues formula, NumPy).

    This is also the exponential map of so(3) that the bundle adjustment's rotation updates
    use. Angles below ``1e-12`` rad use the first-order rotation ``I + [r]x``.

    Args:
        r: (..., 3) rotation vectors.

    Returns:
        (..., 3, 3) rotation matrices.
    """
    r = np.asarray(r, dtype=np.float64)
    theta = np.linalg.norm(r, axis=-1)[..., None, None]
    small = theta < _SMALL_ANGLE
    safe = np.where(small, 1.0, theta)
    K = _cross_matrix(r / safe[..., 0])
    s, c = np.sin(theta), np.cos(theta)
    eye = np.broadcast_to(np.eye(3), K.shape)
    R = eye + s * K + (1 - c) * (K @ K)
    return np.asarray(np.where(small, eye + _cross_matrix(r), R))


def transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The 4x4 rigid transform with rotation ``R`` and translation ``t``.

    Args:
        R: (3, 3) rotation.
        t: (3,) translation (any shape with 3 elements, e.g. OpenCV's (3, 1)).

    Returns:
        (4, 4) transform ``[[R, t], [0, 0, 0, 1]]``.
    """
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t).reshape(3)
    return T


def invert_transform(T: np.ndarray) -> np.ndarray:
    """The inverse of a rigid transform: ``[[R.T, -R.T @ t], [0, 0, 0, 1]]``.

    Args:
        T: (4, 4) rigid transform.

    Returns:
        (4, 4) inverse transform.
    """
    R, t = T[:3, :3], T[:3, 3]
    return transform(R.T, -R.T @ t)
