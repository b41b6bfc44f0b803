"""Propose frames to label next: the least confident predictions, spread over poses and time.

Greedy selection over the predicted frames of a session (``poses.h5``):

1. every frame gets an *uncertainty* ``u``: where the poses carry the network's calibrated
   per-keypoint uncertainty (``extra/uncertainty``, mm, :mod:`freipose.nn.uncertainty`:
   the disagreement of the views and of P0 and P1), the frame's mean of it over the
   largest such mean; else ``u = 1 - mean keypoint confidence``; 1 where the animal was
   not found;
2. the first pick is the most uncertain frame; every next pick maximises
   ``u * (1 - exp(-d / s))``, where ``d`` is the frame's distance to the frames picked so
   far and ``s`` the median distance between frames: the RMS distance between the
   poses centred on their mean (so the same posture elsewhere in the arena is not new);
   frames where the animal was not found are compared by time instead;
3. frames closer than ``min_gap`` frames to a pick (or to an already labeled frame) are
   never picked, so picks are not near-duplicates of each other.

The result lists the frames in the order they were picked (most useful first).

With several animals (poses with an animal axis) a frame is one instant to label for all
of them: its confidence is that of its least confident animal, its pose the animals'
centred poses side by side, and a frame where an animal was not found counts as not found.
"""

from __future__ import annotations

import csv
import logging
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from freipose.errors import FreiPoseError
from freipose.io.atomic import atomic_path
from freipose.io.poses import PoseData

log = logging.getLogger(__name__)


class SelectionError(FreiPoseError):
    """Frames cannot be selected as asked (a bad number of frames or gap)."""


@dataclass(frozen=True, eq=False)
class Selection:
    """Frames proposed for labeling, in pick order.

    Attributes:
        session: session name.
        frame_index: (N,) video frame numbers.
        confidence: (N,) mean keypoint confidence of each pick (0 = not found).
        found: (N,) whether the animal was found in that frame.
        uncertainty: (N,) mean per-keypoint uncertainty (mm) of each pick, NaN where the
            poses carry none.
    """

    session: str
    frame_index: np.ndarray
    confidence: np.ndarray
    found: np.ndarray
    uncertainty: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.frame_index)


def _features(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centred poses (T, K*3) with NaN -> 0, and which frames have a pose (T,)."""
    found = np.isfinite(poses).all(-1).any(-1)
    with np.errstate(invalid="ignore"):
        centre = np.nanmean(np.where(found[:, None, None], poses, 0.0), axis=1, keepdims=True)
    f = np.nan_to_num(poses - centre, nan=0.0)
    return f.reshape(len(poses), -1), found


def _frames_view(poses: np.ndarray, conf: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame: pose features, whether found, and mean confidence (0 where not found).

    Args:
        poses: (T, K, 3), or (T, A, K, 3) with several animals.
        conf: (T, K) or (T, A, K) keypoint confidences (0 where unknown).

    Returns:
        ``(features, found, mean_conf)``: (T, F), (T,) and (T,); with several animals
        the animals' features side by side, found where every animal is, the confidence
        of the least confident animal.
    """
    if poses.ndim == 3:
        feats, found = _features(poses)
        return feats, found, np.where(found, conf.mean(1), 0.0)
    parts = [_features(poses[:, a]) for a in range(poses.shape[1])]
    found = np.logical_and.reduce([f for _, f in parts])
    feats = np.concatenate([x for x, _ in parts], axis=1)
    return feats, found, np.where(found, conf.mean(-1).min(1), 0.0)


def select_frames(
    data: PoseData,
    n: int,
    min_gap: int = 10,
    exclude: Iterable[int] = (),
    session: str | None = None,
) -> Selection:
    """Pick up to ``n`` frames of ``data`` to label next (see the module docstring).

    Args:
        data: the predictions of one session.
        n: how many frames to propose.
        min_gap: fewest frames between two picks, and between a pick and an excluded frame.
        exclude: video frame numbers that are already labeled.
        session: name for the result (default: the provenance's session).

    Raises:
        SelectionError: ``n < 1`` or ``min_gap < 0``.
    """
    if n < 1:
        raise SelectionError(f"the number of frames to select must be at least 1, got {n}")
    if min_gap < 0:
        raise SelectionError(f"min_gap must be >= 0, got {min_gap}")
    name = session or str(data.provenance.get("session", "session"))
    fi = data.frame_index
    T = len(fi)
    conf = np.where(np.isfinite(data.confidence), data.confidence, 0.0).astype(np.float64)
    feats, found, mean_conf = _frames_view(data.poses.astype(np.float64), conf)
    K = max(1, feats.shape[1] // 3)
    sigma = frame_uncertainty(data, found)
    u = _uncertainty_weight(sigma, found) if np.isfinite(sigma).any() else 1.0 - mean_conf
    allowed = np.ones(T, bool)
    ex = np.asarray(sorted({int(e) for e in exclude}), dtype=np.int64)
    if len(ex):
        pos = np.searchsorted(ex, fi)
        near = np.full(T, np.inf)
        for off in (-1, 0):
            j = np.clip(pos + off, 0, len(ex) - 1)
            near = np.minimum(near, np.abs(ex[j] - fi))
        allowed &= near > min_gap
    # distance scale: median RMS distance between random pairs of found frames
    rng = np.random.default_rng(0)
    idx = np.flatnonzero(found)
    if len(idx) >= 2:
        a, b = rng.choice(idx, 512), rng.choice(idx, 512)
        dd = np.sqrt(((feats[a] - feats[b]) ** 2).sum(1) / K)
        scale = float(np.median(dd[dd > 0])) if np.any(dd > 0) else 1.0
    else:
        scale = 1.0
    time_scale = max(1.0, T / max(n, 1))
    dist = np.full(T, np.inf)  # distance to the picks so far
    picks: list[int] = []
    while len(picks) < n:
        gain = u * np.where(np.isfinite(dist), 1.0 - np.exp(-dist / scale), 1.0)
        gain = np.where(allowed, gain, -np.inf)
        best = int(np.argmax(gain))
        if not np.isfinite(gain[best]):
            break
        picks.append(best)
        allowed &= np.abs(fi - fi[best]) > min_gap
        if found[best]:
            d = np.sqrt(((feats - feats[best]) ** 2).sum(1) / K)
            d = np.where(found, d, 2 * scale)
        else:
            d = np.where(
                found, 2 * scale, scale * np.minimum(1.0, np.abs(fi - fi[best]) / time_scale)
            )
        dist = np.minimum(dist, d)
    if len(picks) < n:
        log.warning(
            "%s: only %d frames could be proposed (asked for %d) with min_gap=%d over %d frames",
            name, len(picks), n, min_gap, T,
        )  # fmt: skip
    p = np.asarray(picks, dtype=np.int64)
    return Selection(name, fi[p], mean_conf[p].astype(np.float32), found[p], sigma[p])


def frame_uncertainty(data: PoseData, found: np.ndarray) -> np.ndarray:
    """(T,) each frame's mean per-keypoint uncertainty (mm); NaN where none is known."""
    unc = data.extra.get("uncertainty")
    T = len(data.frame_index)
    if unc is None or np.shape(unc) != np.shape(data.confidence):
        return np.full(T, np.nan)
    u = np.asarray(unc, np.float64).reshape(T, -1)
    ok = np.isfinite(u).any(1) & found
    out = np.full(T, np.nan)
    out[ok] = np.nanmean(u[ok], axis=1)
    return out


def _uncertainty_weight(sigma: np.ndarray, found: np.ndarray) -> np.ndarray:
    """(T,) in [0, 1]: ``sigma`` over its largest value; 1 where the animal was not found."""
    top = float(np.nanmax(sigma))
    w = np.where(np.isfinite(sigma), sigma / top if top > 0 else 0.0, 0.0)
    return np.where(found, w, 1.0)


def write_selection_csv(selections: Iterable[Selection], path: str | Path) -> Path:
    """CSV with columns ``session, frame_index, rank, mean_confidence, found``."""
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["session", "frame_index", "rank", "mean_confidence", "found"])
        for sel in selections:
            for r, (i, c, ok) in enumerate(zip(sel.frame_index, sel.confidence, sel.found)):
                w.writerow([sel.session, int(i), r, f"{float(c):.4f}", int(bool(ok))])
    return Path(path)


def read_selection_csv(path: str | Path) -> list[tuple[str, int]]:
    """(session, frame_index) rows of a selection CSV, in file order."""
    with open(path, newline="") as f:
        return [(row["session"], int(row["frame_index"])) for row in csv.DictReader(f)]


def extract_frames(
    videos: dict[str, Path], frames: Iterable[int], outdir: str | Path
) -> list[Path]:
    """Write ``OUTDIR/<camera>/<frame:08d>.png`` for every camera and frame (for labeling)."""
    import cv2

    from freipose.io.video import FrameSource

    out = []
    frames = sorted(int(i) for i in frames)
    for cam, path in videos.items():
        d = Path(outdir) / cam
        d.mkdir(parents=True, exist_ok=True)
        with FrameSource(path) as src:
            for i in frames:
                p = d / f"{i:08d}.png"
                with atomic_path(p) as tmp:
                    if not cv2.imwrite(str(tmp), src.read(i)):
                        raise OSError(f"cannot write {p}")
                out.append(p)
    return out
