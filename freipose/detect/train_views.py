"""The detector's training views: labeled frames cached at network scale with their boxes."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import cv2
import numpy as np

from freipose.detect.boxes import boxes_from_points, clip_boxes, visible_fraction
from freipose.detect.evaluate import gt_boxes
from freipose.geometry import CameraRig
from freipose.progress import progress_bar


class ViewSettings(Protocol):
    """What :func:`collect_views` reads of a ``DetectorTrainConfig``."""

    box_margin: float
    input_size: int


@dataclass
class ViewImages:
    """Training views cached at network scale: images and boxes (NaN = no animal)."""

    images: list[np.ndarray]
    boxes: np.ndarray  # (N, 4) or (N, M, 4) (several animals) in cached-image pixels


def collect_views(
    samples: Sequence[dict] | Any, indices: Sequence[int], cfg: ViewSettings
) -> ViewImages:
    """Cache the training views of ``samples[i]`` for ``i`` in ``indices`` at network scale.

    Views whose ground-truth box is unknown (no labels) are skipped; views whose box lies
    entirely outside the image are kept as negatives (no animal). Samples of a labels file
    with several animals per instant (``others3d``) carry every animal's box, so that the
    detector learns to find each of them (boxes (N, M, 4), NaN rows for fewer).
    """
    images: list[np.ndarray] = []
    boxes: list[np.ndarray] = []
    for i in progress_bar(indices, desc="loading training views", disable=None, leave=False):
        s = samples[int(i)]
        gt = _all_boxes(s, cfg.box_margin)  # (V, M, 4)
        for v, img in enumerate(s["images"]):
            if not np.isfinite(gt[v, 0]).all():
                continue
            h, w = img.shape[:2]
            frac = visible_fraction(gt[v], (w, h))
            box = np.where((np.nan_to_num(frac) > 0)[:, None], clip_boxes(gt[v], (w, h)), np.nan)
            sc = cfg.input_size / max(w, h)
            small = cv2.resize(
                img,
                (max(1, round(w * sc)), max(1, round(h * sc))),
                interpolation=cv2.INTER_AREA if sc < 1 else cv2.INTER_LINEAR,
            )
            images.append(small)
            boxes.append((box + 0.5) * sc - 0.5)
    return ViewImages(images, stack_boxes(boxes))


def _all_boxes(sample: dict, margin: float) -> np.ndarray:
    """(V, M, 4) the labeled animal's boxes, then the other animals' (``others3d``)."""
    own = gt_boxes(sample, margin)[:, None]
    others = sample.get("others3d")
    rig: CameraRig | None = sample.get("rig")
    if others is None or rig is None or not len(others):
        return own
    p3 = np.asarray(others, dtype=np.float64)  # (A-1, K, 3)
    uv = np.moveaxis(rig.project(p3), 0, 1)  # (A-1, V, K, 2) -> (V, A-1, K, 2)
    return np.concatenate([own, boxes_from_points(uv, margin=margin)], axis=1)


def stack_boxes(boxes: Sequence[np.ndarray]) -> np.ndarray:
    """(N, 4) boxes of one animal each, or (N, M, 4) padded with NaN rows."""
    rows = [np.asarray(b, dtype=np.float64).reshape(-1, 4) for b in boxes]
    m = max((len(r) for r in rows), default=1)
    if m == 1:
        return np.array([r[0] for r in rows]).reshape(-1, 4)
    out = np.full((len(rows), m, 4), np.nan)
    for i, r in enumerate(rows):
        out[i, : len(r)] = r
    return out
