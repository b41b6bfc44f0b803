"""Helpers for the calibration tests: board detections synthesised by exact projection."""

from __future__ import annotations

import numpy as np

from freipose.calibration.bundle import rodrigues
from freipose.calibration.detect import CameraDetections
from freipose.geometry import CameraRig, project


def board_detections(
    rig: CameraRig,
    object_points: np.ndarray,
    board_size: tuple[float, float],
    n_frames: int,
    noise_px: float = 0.2,
    seed: int = 0,
) -> tuple[list[CameraDetections], np.ndarray]:
    """Project a board waved around the rig's target into every camera (no image rendering).

    Returns detections per camera and the true board→world poses (F, 4, 4).
    """
    rng = np.random.default_rng(seed)
    poses = np.zeros((n_frames, 4, 4))
    centroid = np.array([board_size[0] / 2, board_size[1] / 2, 0.0])
    for f in range(n_frames):
        cam = rig[int(rng.integers(len(rig)))]
        zb = -cam.center / np.linalg.norm(cam.center)  # board z points away from the camera
        zb = rodrigues(rng.normal(0, 0.4, 3)) @ zb
        xb = np.cross([0, 0, 1.0], zb)
        xb /= np.linalg.norm(xb)
        R = np.stack([xb, np.cross(zb, xb), zb], 1)
        R = R @ rodrigues(np.array([0, 0, rng.uniform(-0.5, 0.5)]))
        c = rng.uniform([-120, -120, 0], [120, 120, 200])
        poses[f, :3, :3] = R
        poses[f, :3, 3] = c - R @ centroid
        poses[f, 3, 3] = 1
    dets = []
    for cam in rig:
        pts = np.full((n_frames, len(object_points), 2), np.nan)
        for f in range(n_frames):
            R, t = poses[f, :3, :3], poses[f, :3, 3]
            X = object_points @ R.T + t
            if (cam.R @ R[:, 2])[2] < 0.25:  # printed side not facing the camera
                continue
            uv = project(X, cam)
            ok = np.all(np.isfinite(uv), axis=1)
            ok &= (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width - 1)
            ok &= (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height - 1)
            if ok.sum() >= 6:
                pts[f, ok] = uv[ok] + rng.normal(0, noise_px, (int(ok.sum()), 2))
        dets.append(CameraDetections(cam.name, tuple(cam.size), pts))
    return dets, poses


def align_similarity(A: np.ndarray, B: np.ndarray):
    """Similarity (s, R, t) with s R A + t ≈ B for points (N, 3)."""
    ma, mb = A.mean(0), B.mean(0)
    H = (A - ma).T @ (B - mb)
    U, S, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    s = float((S * np.diag(D)).sum() / ((A - ma) ** 2).sum())
    return s, R, mb - s * R @ ma


def rig_errors(est: CameraRig, truth: CameraRig):
    """(centre errors mm (C,), rotation errors deg (C,), focal errors % (C, 2)) after a
    similarity alignment of the camera centres."""
    s, R, t = align_similarity(est.centers, truth.centers)
    c = s * est.centers @ R.T + t
    dc = np.linalg.norm(c - truth.centers, axis=1)
    rot = []
    for e, g in zip(est, truth):
        M = e.R @ R.T @ g.R.T
        rot.append(np.degrees(np.arccos(np.clip((np.trace(M) - 1) / 2, -1, 1))))
    fe = np.array(
        [[e.K[0, 0] / g.K[0, 0] - 1, e.K[1, 1] / g.K[1, 1] - 1] for e, g in zip(est, truth)]
    )
    return dc, np.array(rot), 100 * fe
