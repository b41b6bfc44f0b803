"""Test helpers for the prediction package: a synthetic two-blob session and an estimator
that finds the blobs by colour and triangulates them (deterministic, frame by frame)."""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np

from freipose.geometry import Camera, CameraRig, triangulate
from freipose.io.calibration import save_calibration
from freipose.io.video import VideoWriter
from freipose.nn.dataset import labeled_sample
from freipose.nn.types import Sample
from freipose.predict.estimator import Estimate

KEYPOINTS = ("red", "green")
SIZE = (160, 120)
# BGR colours of the keypoints' blobs
COLORS = ((0, 0, 255), (0, 255, 0))


def small_rig(n: int = 4) -> CameraRig:
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n + 0.3
        pos = (1000 * np.cos(a), 1000 * np.sin(a), 700.0)
        cams.append(Camera.look_at(f"cam{i}", pos, (0, 0, 0), SIZE, 160.0))
    return CameraRig(tuple(cams), {"world": "test"})


def trajectory(n_frames: int) -> np.ndarray:
    """(T, 2, 3) mm: two points circling around the origin."""
    t = np.arange(n_frames) / 10.0
    red = np.stack([120 * np.cos(t), 120 * np.sin(t), 40 + 20 * np.sin(2 * t)], -1)
    green = red + np.array([0.0, 0.0, 80.0])
    return np.stack([red, green], 1)


def make_session(
    folder: Path,
    n_frames: int = 40,
    n_cams: int = 4,
    absent: tuple[int, ...] = (),
    suffix: str = ".mp4",
    fps: float = 25.0,
) -> tuple[CameraRig, np.ndarray]:
    """Write ``folder/cam<i><suffix>`` videos and ``calibration.toml``; the blobs are not
    drawn in frames ``absent``. Returns (rig, true poses (T, 2, 3))."""
    folder.mkdir(parents=True, exist_ok=True)
    rig = small_rig(n_cams)
    truth = trajectory(n_frames)
    uv = rig.project(truth)  # (T, C, 2, 2)
    for c, cam in enumerate(rig):
        with VideoWriter(folder / f"{cam.name}{suffix}", fps, SIZE) as w:
            for i in range(n_frames):
                img = np.full((SIZE[1], SIZE[0], 3), 20, np.uint8)
                if i not in absent:
                    for k, col in enumerate(COLORS):
                        x, y = uv[i, c, k]
                        cv2.circle(img, (int(round(x)), int(round(y))), 4, col, -1, cv2.LINE_AA)
                w.write(img)
    save_calibration(rig, folder / "calibration.toml")
    return rig, truth


def _blob(img: np.ndarray, channel: int) -> tuple[np.ndarray, float]:
    others = [c for c in range(3) if c != channel]
    score = img[..., channel].astype(np.float32) - img[..., others].astype(np.float32).max(-1)
    mask = score > 100
    if mask.sum() < 3:
        return np.full(2, np.nan), 0.0
    ys, xs = np.nonzero(mask)
    w = score[ys, xs]
    return np.array([np.sum(xs * w) / w.sum(), np.sum(ys * w) / w.sum()]), 1.0


class BlobEstimator:
    """Finds a red and a green blob in every view and triangulates them."""

    keypoints = KEYPOINTS
    provenance = {"model": "blob-test-estimator"}

    def __init__(self) -> None:
        self.calls = 0
        self.frames = 0

    def __call__(self, images, rig):
        self.calls += 1
        B = images[0].shape[0]
        C, K = len(rig), len(KEYPOINTS)
        self.frames += B
        p2 = np.full((B, C, K, 2), np.nan)
        c2 = np.zeros((B, C, K))
        for c in range(C):
            for b in range(B):
                for k, ch in enumerate((2, 1)):
                    p2[b, c, k], c2[b, c, k] = _blob(images[c][b], ch)
        poses = np.full((B, K, 3), np.nan)
        conf = np.zeros((B, K))
        for b in range(B):
            for k in range(K):
                ok = c2[b, :, k] > 0
                if ok.sum() >= 2:
                    sub = rig.subset([rig.names[i] for i in np.flatnonzero(ok)])
                    poses[b, k] = triangulate(p2[b, ok, k], sub)
                    conf[b, k] = ok.mean()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN frames give NaN
            center = np.nanmean(poses, axis=1)
            mid = np.nanmean(p2, axis=2)  # (B, C, 2)
        boxes = np.concatenate([mid - 20, mid + 20], -1)
        return Estimate(poses, conf, p2, c2, boxes, center)


def h5_equal(a: Path, b: Path, ignore_attrs: tuple[str, ...] = ()) -> list[str]:
    """Differences between two HDF5 files (datasets bitwise incl. NaN, attributes)."""
    import h5py

    diffs: list[str] = []
    with h5py.File(a, "r") as fa, h5py.File(b, "r") as fb:

        def attrs(x, y, where):
            ka, kb = set(x.attrs) - set(ignore_attrs), set(y.attrs) - set(ignore_attrs)
            if ka != kb:
                diffs.append(f"{where}: attrs {sorted(ka ^ kb)}")
            for k in ka & kb:
                va, vb = x.attrs[k], y.attrs[k]
                if not np.array_equal(np.asarray(va), np.asarray(vb)):
                    diffs.append(f"{where}: attr {k} {va!r} != {vb!r}")

        attrs(fa, fb, "/")
        names_a, names_b = [], []
        fa.visit(names_a.append)
        fb.visit(names_b.append)
        if sorted(names_a) != sorted(names_b):
            diffs.append(f"objects differ: {sorted(set(names_a) ^ set(names_b))}")
        for n in names_a:
            if n not in fb:
                continue
            oa, ob = fa[n], fb[n]
            attrs(oa, ob, n)
            if isinstance(oa, h5py.Dataset):
                x, y = oa[()], ob[()]
                if x.shape != y.shape or x.dtype != y.dtype:
                    diffs.append(f"{n}: {x.shape} {x.dtype} vs {y.shape} {y.dtype}")
                elif x.dtype.kind == "f":
                    if not np.array_equal(x, y, equal_nan=True):
                        diffs.append(f"{n}: values differ")
                elif not np.array_equal(x, y):
                    diffs.append(f"{n}: values differ")
    return diffs


# -- a toy animal for the network end-to-end test ------------------------------------------

TOY_TEMPLATE = np.array([[60.0, 0, 30], [0, 40, 20], [0, -40, 20], [-60, 0, 30], [0, 0, 70]])
TOY_COLORS = [(255, 40, 40), (40, 255, 40), (40, 40, 255), (255, 255, 40), (255, 40, 255)]
TOY_KEYPOINTS = tuple(f"kp{i}" for i in range(len(TOY_TEMPLATE)))


def toy_rig(n: int = 3, size=(160, 120), focal: float = 220.0) -> CameraRig:
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        pos = (700 * np.cos(a), 700 * np.sin(a), 400.0)
        cams.append(Camera.look_at(f"cam{i}", pos, (0, 0, 0), size, focal))
    return CameraRig(tuple(cams), {"world": "toy arena"})


def toy_pose(angle: float, shift: np.ndarray) -> np.ndarray:
    R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    return TOY_TEMPLATE @ R.T + np.array([shift[0], shift[1], 0.0])


def toy_render(pts: np.ndarray, rig: CameraRig, rng: np.random.Generator) -> list[np.ndarray]:
    from freipose.geometry import project

    images = []
    for cam in rig:
        w, h = cam.size
        img = np.clip(rng.normal(110, 6, (h, w, 3)), 0, 255).astype(np.uint8)
        uv = project(pts, cam)
        depth = (pts @ cam.R.T + cam.t)[:, 2]
        px = [(int(round(u)), int(round(v))) for u, v in uv]
        body = max(2, int(round(cam.K[0, 0] * 10 / depth.mean())))
        for k in range(len(pts) - 1):  # a dark body joins the discs into one blob
            cv2.line(img, px[k], px[-1], (40, 40, 40), body)
        for k in np.argsort(-depth):
            r = max(2, int(round(cam.K[0, 0] * 12 / depth[k])))
            cv2.circle(img, px[k], r, TOY_COLORS[k], -1)
        images.append(img)
    return images


def toy_training_samples(n: int, rig: CameraRig, seed: int = 0) -> list[Sample]:
    """Labeled samples (``MultiViewDataset`` format) of the toy animal at random poses."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        pts = toy_pose(rng.uniform(0, 2 * np.pi), rng.uniform(-50, 50, 2))
        pts = pts + rng.normal(0, 3, pts.shape)
        images = toy_render(pts, rig, rng)
        out.append(
            labeled_sample(
                rig, images, rig.project(pts), pts, session="train", frame_index=i, index=i
            )
        )
    return out


def toy_session(folder: Path, rig: CameraRig, n_frames: int, seed: int = 1, fps: float = 30.0):
    """Videos (lossless .mkv) of the toy animal walking; returns the true poses (T, 5, 3)."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    t = np.arange(n_frames) / fps
    truth = np.stack(
        [toy_pose(1.3 * ti, np.array([40 * np.cos(0.8 * ti), 40 * np.sin(1.1 * ti)])) for ti in t]
    )
    frames = [toy_render(p, rig, rng) for p in truth]
    for c, cam in enumerate(rig):
        with VideoWriter(folder / f"{cam.name}.mkv", fps, cam.size) as w:
            for f in frames:
                w.write(f[c])
    save_calibration(rig, folder / "calibration.toml")
    return truth
