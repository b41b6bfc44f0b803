"""Helpers for the calibration tests: board detections synthesised by exact projection."""

from __future__ import annotations

import numpy as np

from freipose.calibration.detect import CameraDetections
from freipose.geometry import CameraRig, project
from freipose.geometry.alignment import rig_errors as geometry_rig_errors
from freipose.geometry.transforms import rodrigues


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


def rig_errors(est: CameraRig, truth: CameraRig):
    """(centre errors mm (C,), rotation errors deg (C,), focal errors % (C, 2)) after a
    similarity alignment of the camera centres."""
    dc, rot, fe, _ = geometry_rig_errors(est, truth)
    return dc, rot, fe


def rendered_view(camera: int, n_poses: int, seed: int, keep: slice):
    """Board frames rendered by the synthetic-scene renderer in one camera (index ``camera``)
    of the 640 x 480 four-camera default rig: the default ChArUco board at
    ``board_poses(n_poses, rng=seed)[keep]``, image noise seeded with ``seed``.

    Returns ``(one-camera rig, board, poses (F, 4, 4), BGR images [F])``.
    """
    from freipose.synth.board import board_poses, default_board, render_board_frames
    from freipose.synth.rig import default_rig

    full = default_rig(4, size=(640, 480))
    rig = CameraRig((full[camera],), full.metadata)
    board = default_board()
    poses = board_poses(n_poses, rng=seed, board_size_mm=board.size_mm)[keep]
    images = render_board_frames(rig, board, poses, seed=seed)[rig[0].name]
    return rig, board, poses, images
