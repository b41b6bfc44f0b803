"""A tiny hand-made multi-view scene for the detector tests: a bright ellipsoid "animal"
walking over a textured, static background, seen by a ring of small cameras."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from freipose.geometry import Camera, CameraRig

KEYPOINTS = ("nose", "tail", "left", "right", "top", "bottom")


def small_rig(
    n: int = 4, size: tuple[int, int] = (160, 120), focal: float = 160.0, phase: float = 0.0
):
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n + phase
        pos = (900 * np.cos(a), 900 * np.sin(a), 700.0)
        cams.append(Camera.look_at(f"cam{i}", pos, (0, 0, 0), size, focal))
    return CameraRig(tuple(cams), {"world": "test scene"})


def render_scene(rig: CameraRig, n_frames: int, seed: int = 0) -> dict:
    """Frames (T lists of C BGR images), points3d (T, K, 3), points2d (T, C, K, 2), centres
    (T, 3), silhouettes (T, C, 4) and the per-camera backgrounds."""
    rng = np.random.default_rng(seed)
    axes = np.array([90.0, 40.0, 35.0])
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 24), np.linspace(0, np.pi, 12))
    sphere = np.stack([np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)], -1).reshape(-1, 3)
    unit_kp = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1.0]])
    backgrounds = []
    for cam in rig:
        w, h = cam.size
        noise = rng.integers(0, 120, (h // 4 + 1, w // 4 + 1, 3)).astype(np.uint8)
        bg = cv2.resize(noise, (w, h), interpolation=cv2.INTER_LINEAR)[:h, :w]
        backgrounds.append(bg)
    frames, p3, centres, silhouettes = [], [], [], []
    for t in range(n_frames):
        ang = 2 * np.pi * t / max(n_frames, 1)
        c = np.array([150 * np.cos(ang) + rng.normal(0, 20), 120 * np.sin(2 * ang), 40.0])
        yaw = ang + np.pi / 2 + rng.normal(0, 0.3)
        Rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
        surf = c + (sphere * axes) @ Rz.T
        kp = c + (unit_kp * axes) @ Rz.T
        views = []
        proj = rig.project(surf)  # (C, P, 2)
        silhouettes.append(np.concatenate([proj.min(1), proj.max(1)], -1))
        for ci in range(len(rig)):
            img = backgrounds[ci].copy()
            uv = proj[ci]
            hull = cv2.convexHull(np.round(uv * 4).astype(np.int32))
            cv2.fillConvexPoly(img, hull, (210, 230, 250), lineType=cv2.LINE_AA, shift=2)
            views.append(img)
        frames.append(views)
        p3.append(kp)
        centres.append(c)
    p3 = np.array(p3)
    return {
        "frames": frames,
        "points3d": p3,
        "points2d": rig.project(p3),
        "centres": np.array(centres),
        "silhouettes": np.array(silhouettes),  # (T, C, 4) boxes of the projected body
        "backgrounds": backgrounds,
    }


def write_session(folder: Path, rig: CameraRig, n_frames: int, seed: int = 0) -> dict:
    """Videos (lossless .mkv), calibration.toml and labels.h5 of a rendered scene."""
    from freipose.io.calibration import save_calibration
    from freipose.io.labels import LabelSet, SessionInfo, write_labels_h5
    from freipose.io.video import VideoWriter

    folder.mkdir(parents=True, exist_ok=True)
    scene = render_scene(rig, n_frames, seed)
    for ci, cam in enumerate(rig):
        with VideoWriter(folder / f"{cam.name}.mkv", 30.0, cam.size) as w:
            for t in range(n_frames):
                w.write(scene["frames"][t][ci])
    save_calibration(rig, folder / "calibration.toml")
    labels = LabelSet(
        session=np.array(["s"] * n_frames),
        frame_index=np.arange(n_frames),
        points2d=scene["points2d"],
        points3d=scene["points3d"],
        cameras=tuple(rig.names),
        keypoints=KEYPOINTS,
        sessions={"s": SessionInfo(rig, {c: f"{c}.mkv" for c in rig.names}, 30.0)},
    )
    write_labels_h5(labels, folder / "labels.h5")
    scene["labels"] = labels
    return scene


@pytest.fixture(scope="session")
def scene_rig() -> CameraRig:
    return small_rig()


@pytest.fixture(scope="session")
def scene(scene_rig: CameraRig) -> dict:
    return render_scene(scene_rig, 12, seed=3)


@pytest.fixture(scope="session")
def session_dir(tmp_path_factory: pytest.TempPathFactory, scene_rig: CameraRig) -> Path:
    folder = tmp_path_factory.mktemp("detect_session")
    write_session(folder, scene_rig, 16, seed=5)
    return folder
