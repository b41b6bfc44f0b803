"""Comparing a calibrated rig with a reference rig: similarity alignment and per-camera errors.

Two calibrations of the same cameras differ by the choice of world frame (and, if a board
was mis-sized, by scale). The frames are aligned by the similarity that best maps one set
of camera centres onto the other; the errors are measured after that alignment.
"""

from __future__ import annotations

import numpy as np

from freipose.geometry.camera import CameraRig


def align_similarity(A: np.ndarray, B: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity ``(s, R, t)`` with ``s R A + t ≈ B`` for points A, B (N, 3) (Umeyama)."""
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    if A.shape != B.shape or A.ndim != 2 or A.shape[1] != 3:
        raise ValueError(f"need two (N, 3) point sets of one shape, got {A.shape} and {B.shape}")
    ma, mb = A.mean(0), B.mean(0)
    H = (A - ma).T @ (B - mb)
    U, S, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(Vt.T @ U.T)))])
    R = Vt.T @ D @ U.T
    s = float((S * np.diag(D)).sum() / ((A - ma) ** 2).sum())
    return s, R, mb - s * R @ ma


def camera_errors(
    centers: np.ndarray, rotations: np.ndarray, focals: np.ndarray, truth: CameraRig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[float, np.ndarray, np.ndarray]]:
    """Errors of estimated cameras against ``truth`` (same cameras, same order).

    Args:
        centers: (C, 3) estimated camera centres (mm, estimated world).
        rotations: (C, 3, 3) estimated world→camera rotations.
        focals: (C,) focal lengths compared with the true fx, or (C, 2) (fx, fy).
        truth: the reference rig.

    Returns:
        ``(center_mm (C,), rotation_deg (C,), focal_percent (C,) or (C, 2), (s, R, t))``,
        where ``(s, R, t)`` maps estimated to true world coordinates.
    """
    s, R, t = align_similarity(centers, truth.centers)
    c = s * np.asarray(centers) @ R.T + t
    center_mm = np.linalg.norm(c - truth.centers, axis=1)
    rot = []
    for Re, g in zip(rotations, truth):
        M = np.asarray(Re) @ R.T @ g.R.T
        rot.append(np.degrees(np.arccos(np.clip((np.trace(M) - 1) / 2, -1, 1))))
    f = np.asarray(focals, dtype=np.float64)
    ref = truth.K[:, [0, 1], [0, 1]] if f.ndim == 2 else truth.K[:, 0, 0]
    return center_mm, np.array(rot), 100 * (f / ref - 1), (s, R, t)


def rig_errors(
    est: CameraRig, truth: CameraRig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[float, np.ndarray, np.ndarray]]:
    """:func:`camera_errors` of a calibrated rig (cameras matched by name), focal as (fx, fy)."""
    est = est.subset(truth.names)
    return camera_errors(est.centers, est.R, est.K[:, [0, 1], [0, 1]], truth)
