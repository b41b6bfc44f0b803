"""Ground-truth boxes from labels, and detection metrics.

* The **ground-truth box** of a view is the bounding box of its labeled 2D points and the
  projections of the labeled 3D points (when the session is calibrated), widened by a
  margin (a fraction of the longer side), the same rule training uses.
* A view **shows the animal** when at least ``min_visible`` (default half) of that box lies
  inside the image; recall counts those views, comparing with the box clipped to the image.
* The **ground-truth 3D centre** is the DLT triangulation of the (unclipped) ground-truth
  box centres of all views: the point the detector's box centres should triangulate to.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from freipose.detect.base import BoxSource
from freipose.detect.boxes import (
    box_centers,
    box_iou,
    boxes_from_points,
    clip_boxes,
    visible_fraction,
)
from freipose.detect.multiview import ConsistencyConfig, consistent_detection
from freipose.geometry import CameraRig, triangulate

log = logging.getLogger(__name__)


def gt_boxes(sample: dict, margin: float = 0.1) -> np.ndarray:
    """Unclipped ground-truth boxes (V, 4) of one ``MultiViewDataset`` sample (NaN = unlabeled)."""
    p2 = np.asarray(sample["points2d"], dtype=np.float64)  # (V, K, 2)
    pts = p2
    rig: CameraRig | None = sample.get("rig")
    p3 = np.asarray(sample["points3d"], dtype=np.float64)
    if rig is not None and np.isfinite(p3).all(-1).sum() >= 2:
        proj = rig.project(p3[np.isfinite(p3).all(-1)])  # (V, K', 2)
        pts = np.concatenate([p2, proj], axis=1)
    return boxes_from_points(pts, margin=margin)


def image_sizes(sample: dict) -> list[tuple[int, int]]:
    """(width, height) per view, from the images or else the rig."""
    if sample.get("images"):
        return [(im.shape[1], im.shape[0]) for im in sample["images"]]
    rig = sample.get("rig")
    if rig is None:
        raise ValueError("sample has neither images nor a calibration to tell its image sizes")
    return [(int(c.size[0]), int(c.size[1])) for c in rig]


@dataclass(frozen=True)
class DetectionMetrics:
    """Detection quality over an evaluation set.

    Attributes:
        recall: fraction of views showing the animal whose multi-view consistent box has
            IoU >= 0.5 with the ground truth (labels of several animals per instant: any
            of the view's boxes, the centre that of the 3D animal hypothesis nearest it).
        recall_top1: the same for each view's best detector box alone (no consistency).
        median_center_error: median distance (mm) of the 3D centre from the ground-truth
            centre over time instants with both (NaN when uncalibrated).
        center_rate: fraction of time instants that got a 3D centre.
        mean_agree: mean number of agreeing views per time instant.
        n_views: views showing the animal; n_instants: time instants evaluated.
    """

    recall: float
    recall_top1: float
    median_center_error: float
    center_rate: float
    mean_agree: float
    n_views: int
    n_instants: int

    def summary(self) -> str:
        """The metrics as one line of text (what ``freipose train --stage detector`` prints)."""
        return (
            f"the animal's 3D centre found in {100 * self.center_rate:.1f}% of "
            f"{self.n_instants} time instants (median 3D centre error "
            f"{self.median_center_error:.2f} mm, {self.mean_agree:.2f} agreeing views on "
            "average); per view, the box overlaps the "
            f"true box (IoU >= 0.5) in {100 * self.recall:.1f}% of {self.n_views} views "
            f"(recall@IoU0.5 {self.recall:.3f}; the best box of each view alone: "
            f"{self.recall_top1:.3f})"
        )


def evaluate_source(
    source: BoxSource,
    samples: Iterable[dict],
    margin: float = 0.1,
    consistency: ConsistencyConfig | None = None,
    min_visible: float = 0.5,
) -> DetectionMetrics:
    """Run ``source`` and the multi-view step on labeled samples and score the boxes.

    Args:
        source: the box source to evaluate.
        samples: ``MultiViewDataset`` samples with images (calibrated sessions get the
            multi-view step and centre errors; uncalibrated ones only ``recall_top1``).
        margin: the ground-truth box margin (use the training value).
        consistency: multi-view settings.
        min_visible: the fraction of the ground-truth box inside the image for a view to
            count as showing the animal.
    """
    hits, hits1, n_views, errors, agrees = 0, 0, 0, [], []
    n_inst = n_center = 0
    for s in samples:
        images = s["images"]
        if not images:
            raise ValueError("evaluation needs samples with images (load_images=True)")
        names = list(s.get("camera_names") or (s["rig"].names if s.get("rig") else []))
        cands = source.propose(images, names)
        gt = gt_boxes(s, margin)
        sizes = image_sizes(s)
        vis = np.array([visible_fraction(gt[v], sizes[v]) for v in range(len(images))])
        shown = np.nan_to_num(vis) >= min_visible
        gt_clip = np.stack([clip_boxes(gt[v], sizes[v]) for v in range(len(images))])
        top1 = np.array([c.boxes[0] if len(c) else np.full(4, np.nan) for c in cands])
        hits1 += int(np.sum(np.nan_to_num(box_iou(top1, gt_clip))[shown] >= 0.5))
        n_views += int(shown.sum())
        rig = s.get("rig")
        n_inst += 1
        if rig is None:
            hits += int(np.sum(np.nan_to_num(box_iou(top1, gt_clip))[shown] >= 0.5))
            continue
        gt_center = triangulate(box_centers(gt), rig)
        if s.get("others3d") is not None:  # several animals: the one nearest this animal
            det = _among_animals(cands, rig, gt_center)
            any_box = [(np.nan_to_num(box_iou(c.boxes, gt_clip[v])) >= 0.5).any() for v, c in
                       enumerate(cands)]  # fmt: skip
            hits += int(np.sum(np.array(any_box, bool)[shown]))
        else:
            det = consistent_detection(cands, rig, consistency)
            hits += int(np.sum(np.nan_to_num(box_iou(det.boxes, gt_clip))[shown] >= 0.5))
        agrees.append(det.n_agree)
        if np.isfinite(det.center).all():
            n_center += 1
            if np.isfinite(gt_center).all():
                errors.append(float(np.linalg.norm(det.center - gt_center)))
    return DetectionMetrics(
        recall=hits / n_views if n_views else float("nan"),
        recall_top1=hits1 / n_views if n_views else float("nan"),
        median_center_error=float(np.median(errors)) if errors else float("nan"),
        center_rate=n_center / len(agrees) if agrees else float("nan"),
        mean_agree=float(np.mean(agrees)) if agrees else float("nan"),
        n_views=n_views,
        n_instants=n_inst,
    )


@dataclass(frozen=True)
class _Found:
    center: np.ndarray
    n_agree: int


def _among_animals(cands: Sequence[Any], rig: CameraRig, center: np.ndarray) -> _Found:
    """The 3D animal hypothesis of several animals' boxes nearest ``center`` (NaN: none)."""
    from freipose.detect.multi import detect_animals

    found = detect_animals(cands, rig)
    if not len(found.centers) or not np.isfinite(center).all():
        return _Found(np.full(3, np.nan), 0)
    h = int(np.argmin(np.linalg.norm(found.centers - center, axis=-1)))
    return _Found(found.centers[h], int(found.n_views[h]))


def measure_fps(
    detector, image_size: tuple[int, int] = (640, 480), n_images: int = 24, batch_size: int = 8
) -> float:
    """Images per second of ``detector.propose`` (letterboxing included) on random frames."""
    rng = np.random.default_rng(0)
    w, h = image_size
    imgs = [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for _ in range(batch_size)]
    detector.propose(imgs[:2])  # warm-up
    t0 = time.perf_counter()
    done = 0
    while done < n_images:
        detector.propose(imgs, batch_size=batch_size)
        done += batch_size
    return done / (time.perf_counter() - t0)


def measure_speed(detector, sets: Sequence[Any]) -> tuple[float, str]:
    """Images per second of ``detector`` at the image size of the datasets' first camera.

    Args:
        detector: a :class:`~freipose.detect.detector.Detector` on the CPU.
        sets: labeled datasets (``MultiViewDataset``); 640x480 where none is calibrated.

    Returns:
        ``(fps, how)``: the speed and what it was measured on (size, threads).
    """
    import torch

    size = (640, 480)
    rigs = [ds.labels.rig_for(n) for ds in sets for n in ds.labels.sessions]
    rig = next((r for r in rigs if r is not None and len(r)), None)
    if rig is not None:
        size = tuple(rig[0].size)
    how = "as the training videos" if rig is not None else "the labels have no calibrated camera"
    fps = measure_fps(detector, size)
    return fps, f"{size[0]}x{size[1]} images, {how}; {torch.get_num_threads()} threads"
