"""Tiny in-memory multi-view samples for the network tests (MultiViewDataset format).

Keypoints of a random rigid "animal" are drawn as coloured discs on noisy grey frames of
a small circle rig; every label is exact and visible.
"""

from __future__ import annotations

import cv2
import numpy as np

from freipose.geometry import project
from freipose.nn.dataset import labeled_sample
from freipose.nn.types import Batch, Sample
from freipose.skeleton import Skeleton
from freipose.testing import make_circle_rig

TEMPLATE = np.array([[60.0, 0, 30], [0, 40, 20], [0, -40, 20], [-60, 0, 30], [0, 0, 70]])
COLORS = [(255, 40, 40), (40, 255, 40), (40, 40, 255), (255, 255, 40), (255, 40, 255)]


def toy_skeleton() -> Skeleton:
    return Skeleton(name="toy", keypoints=tuple(f"kp{i}" for i in range(len(TEMPLATE))))


def toy_samples(n: int, seed: int = 0, cams: int = 3, size=(160, 120), focal=220.0) -> list[Sample]:
    rig = make_circle_rig(n=cams, radius=700.0, height=400.0, size=size, focal=focal)
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        a = rng.uniform(0, 2 * np.pi)
        R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        pts = (
            TEMPLATE @ R.T
            + np.array([*rng.uniform(-60, 60, 2), 0.0])
            + rng.normal(0, 5, TEMPLATE.shape)
        )
        images, p2 = [], []
        for cam in rig:
            img = np.clip(rng.normal(110, 12, (size[1], size[0], 3)), 0, 255).astype(np.uint8)
            uv = project(pts, cam)
            depth = (pts @ cam.R.T + cam.t)[:, 2]
            for k in np.argsort(-depth):
                r = max(2, int(round(focal * 12 / depth[k])))
                cv2.circle(img, (int(round(uv[k, 0])), int(round(uv[k, 1]))), r, COLORS[k], -1)
            images.append(img)
            p2.append(uv)
        out.append(
            labeled_sample(rig, images, np.array(p2), pts, session="toy", frame_index=i, index=i)
        )
    return out


def toy_batch(model, n: int = 2, cams: int = 3, seed: int = 0) -> Batch:
    """A collated, unaugmented batch of ``n`` toy samples for the model config ``model``."""
    from freipose.nn.data import collate_prepared, prepare_sample

    return collate_prepared([prepare_sample(s, model) for s in toy_samples(n, seed, cams)])


def write_toy_labels(folder, samples: list[dict]):
    """Write samples as image folders + labels.h5 (one session); returns the labels path."""
    from pathlib import Path

    from freipose.io.labels import LabelSet, SessionInfo, write_labels_h5

    folder = Path(folder)
    rig = samples[0]["rig"]
    videos = {}
    for v, name in enumerate(rig.names):
        d = folder / "frames" / name
        d.mkdir(parents=True, exist_ok=True)
        for i, s in enumerate(samples):
            cv2.imwrite(str(d / f"{i:05d}.png"), s["images"][v])
        videos[name] = f"frames/{name}"
    n = len(samples)
    labels = LabelSet(
        session=np.array(["toy"] * n, dtype=object),
        frame_index=np.arange(n),
        points2d=np.stack([s["points2d"] for s in samples]),
        points3d=np.stack([s["points3d"] for s in samples]),
        cameras=tuple(rig.names),
        keypoints=toy_skeleton().keypoints,
        sessions={"toy": SessionInfo(calibration=rig, videos=videos, fps=30.0)},
    )
    path = folder / "labels.h5"
    write_labels_h5(labels, path)
    return path
