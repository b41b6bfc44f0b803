"""Boxes that agree across views: a robust 3D centre and cube crops for every camera.

Per time instant, every view proposes a few candidate boxes (best first). The 3D centre
is found by exhaustive hypothesise-and-verify over *candidates*, not just the top box per
view:

1. every pair of views and every pair of their candidates (the top ``max_candidates``
   with score >= ``min_score``) proposes a 3D point by DLT triangulation of the two box
   centres (:func:`freipose.geometry.triangulate`);
2. a view *agrees* with a proposal when one of its candidates' centres lies within a
   tolerance of the proposal's projection; the tolerance scales with the candidate's size
   (``max(min_tolerance_px, rel_tolerance * sqrt(w * h))``), since a box centre is only as
   exact as the box;
3. the proposal with the most agreeing views wins (ties: the larger summed
   ``score * (1 - error / tolerance)``); with fewer than ``min_views`` there is no centre;
4. per agreeing view the box minimising ``error / tolerance / sqrt(score + 0.001)`` is
   chosen (the original FreiPose's rule, normalised by the tolerance), and the centre is
   re-triangulated from the chosen boxes (score-weighted DLT plus nonlinear refinement,
   :func:`freipose.geometry.triangulate_weighted`); one more verify/refit round lets views
   join or leave;
5. views that do not agree (the detector missed, or found something else) get a
   *replacement* box: a square at the projected centre whose size is the animal's size in
   mm (median over the agreeing views) seen at that view's depth; their score is 0;
6. crop boxes for the pose network are the projections of a fixed-size cube around the
   centre (:func:`freipose.geometry.crops.cube_crop_boxes`) in every view, so crops are
   consistent across views whether or not the detector found the animal there.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from freipose.detect.base import BoxSource, Candidates, DetectConfigError
from freipose.detect.boxes import box_centers, box_sizes
from freipose.geometry import CameraRig, project_rig, triangulate, triangulate_weighted
from freipose.geometry.crops import cube_crop_boxes

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ConsistencyConfig:
    """Settings of the multi-view consistency step (see the module docstring)."""

    cube_size: float = 400.0
    max_candidates: int = 3
    min_score: float = 0.1
    rel_tolerance: float = 0.25
    min_tolerance_px: float = 8.0
    min_views: int = 2

    def __post_init__(self) -> None:
        if not self.cube_size > 0:
            raise DetectConfigError(f"cube_size must be positive (mm), got {self.cube_size}")
        if self.max_candidates < 1:
            raise DetectConfigError(f"max_candidates must be >= 1, got {self.max_candidates}")
        if self.min_views < 2:
            raise DetectConfigError(
                f"min_views must be >= 2 (a 3D point needs two views), got {self.min_views}"
            )
        if self.rel_tolerance < 0 or self.min_tolerance_px <= 0:
            raise DetectConfigError("rel_tolerance must be >= 0 and min_tolerance_px > 0")


@dataclass(frozen=True, eq=False)
class MultiViewDetection:
    """The consistent detection of one time instant over C cameras.

    Attributes:
        boxes: (C, 4) per view the chosen detector box where the view agreed, else a
            replacement box around the projected centre; NaN where there is no centre and
            the view had no candidate.
        scores: (C,) detector score of the chosen box; 0 for replacement boxes.
        center: (3,) world mm; NaN when fewer than ``min_views`` views agreed.
        n_agree: how many views agreed with the centre (0 without a centre).
        agree: (C,) which views agreed.
        crop_boxes: (C, 4) square boxes around the projected cube (NaN without a centre).
    """

    boxes: np.ndarray
    scores: np.ndarray
    center: np.ndarray
    n_agree: int
    agree: np.ndarray
    crop_boxes: np.ndarray


def _padded(cands: Sequence[Candidates], cfg: ConsistencyConfig) -> tuple[np.ndarray, ...]:
    """Top candidates per view as (C, M, 4) boxes, (C, M) scores, NaN-padded."""
    c, m = len(cands), cfg.max_candidates
    boxes = np.full((c, m, 4), np.nan)
    scores = np.full((c, m), np.nan)
    for i, cd in enumerate(cands):
        ok = (cd.scores >= cfg.min_score) & np.isfinite(cd.boxes).all(-1)
        b, s = cd.boxes[ok][:m], cd.scores[ok][:m]
        boxes[i, : len(s)] = b
        scores[i, : len(s)] = s
    return boxes, scores


def _verify(
    X: np.ndarray, rig: CameraRig, centres: np.ndarray, scores: np.ndarray, tol: np.ndarray
):
    """For proposals X (H, 3): per view agreement (H, C), best candidate (H, C), quality (H,)."""
    uv = project_rig(X[:, None, :], rig)[:, :, 0, :]  # (H, C, 2), NaN behind a camera
    err = np.linalg.norm(uv[:, :, None, :] - centres[None], axis=-1)  # (H, C, M)
    inl = np.isfinite(err) & (err < tol[None])
    rank = np.where(
        inl, err / tol[None] / np.sqrt(np.nan_to_num(scores, nan=0.0)[None] + 1e-3), np.inf
    )
    best = np.argmin(rank, axis=-1)  # (H, C)
    agree = inl.any(-1)
    gain = np.where(inl, np.nan_to_num(scores)[None] * (1 - err / tol[None]), 0.0).max(-1)
    return agree, best, gain.sum(-1), err


def consistent_detection(
    candidates: Sequence[Candidates], rig: CameraRig, config: ConsistencyConfig | None = None
) -> MultiViewDetection:
    """The multi-view consistent boxes, 3D centre and cube crops of one time instant.

    Args:
        candidates: one :class:`Candidates` per camera of ``rig`` (same order).
        rig: the cameras (C).
        config: tolerances, cube size, etc.

    Returns:
        a :class:`MultiViewDetection`.
    """
    cfg = config or ConsistencyConfig()
    c = len(rig)
    if len(candidates) != c:
        raise ValueError(
            f"expected candidates for {c} cameras ({rig.names}), got {len(candidates)}"
        )
    boxes, scores = _padded(candidates, cfg)
    centres = box_centers(boxes)  # (C, M, 2)
    sz = box_sizes(boxes)
    tol = np.maximum(
        cfg.min_tolerance_px, cfg.rel_tolerance * np.sqrt(np.abs(sz[..., 0] * sz[..., 1]))
    )
    tol = np.where(np.isfinite(scores), tol, np.nan)

    # 1. Proposals from every pair of views and every pair of their candidates.
    m = cfg.max_candidates
    obs = []
    for i, j in itertools.combinations(range(c), 2):
        for a, b in itertools.product(range(m), range(m)):
            if np.isfinite(scores[i, a]) and np.isfinite(scores[j, b]):
                p = np.full((c, 2), np.nan)
                p[i], p[j] = centres[i, a], centres[j, b]
                obs.append(p)
    center = np.full(3, np.nan)
    agree = np.zeros(c, dtype=bool)
    chosen = np.zeros(c, dtype=np.int64)
    if obs:
        X = triangulate(np.stack(obs), rig)  # (H, 3)
        X = X[np.isfinite(X).all(-1)]
        if len(X):
            # 2-3. Verify every proposal; most agreeing views, then best quality.
            ag, best, quality, _ = _verify(X, rig, centres, scores, tol)
            count = ag.sum(-1)
            h = int(np.lexsort((quality, count))[-1])
            if count[h] >= cfg.min_views:
                agree, chosen = ag[h], best[h]
                # 4. Refit from the chosen boxes, then verify and refit once more. The
                # weighted DLT suffices: box centres are not projections of one 3D point,
                # so a pixel-optimal polish of their triangulation gains nothing.
                for _ in range(2):
                    pts = np.where(agree[:, None], centres[np.arange(c), chosen], np.nan)
                    w = np.where(agree, scores[np.arange(c), chosen], 0.0)
                    Xr = triangulate_weighted(pts, np.maximum(w, 1e-3) * agree, rig)
                    if not np.isfinite(Xr).all():
                        break
                    ag2, best2, _, _ = _verify(Xr[None], rig, centres, scores, tol)
                    if ag2[0].sum() < cfg.min_views:
                        break
                    center, agree, chosen = Xr, ag2[0], best2[0]
                if not np.isfinite(center).all():
                    center = X[h]

    out_boxes = np.full((c, 4), np.nan)
    out_scores = np.full(c, np.nan)
    if np.isfinite(center).all():
        idx = np.arange(c)
        out_boxes[agree] = boxes[idx, chosen][agree]
        out_scores[agree] = scores[idx, chosen][agree]
        _replace_missing(out_boxes, out_scores, agree, center, rig)
        crops = cube_crop_boxes(rig, center, cfg.cube_size)
    else:
        agree[:] = False
        for i, cd in enumerate(candidates):  # fall back to each view's best box
            if len(cd):
                out_boxes[i], out_scores[i] = cd.boxes[0], cd.scores[0]
        crops = np.full((c, 4), np.nan)
    return MultiViewDetection(out_boxes, out_scores, center, int(agree.sum()), agree, crops)


def _replace_missing(
    boxes: np.ndarray, scores: np.ndarray, agree: np.ndarray, center: np.ndarray, rig: CameraRig
) -> None:
    """Fill non-agreeing views with square boxes of the animal's size at the projected centre."""
    depth = np.einsum("cij,j->ci", rig.R, center)[:, 2] + rig.t[:, 2]  # (C,)
    f = np.sqrt(np.abs(rig.K[:, 0, 0] * rig.K[:, 1, 1]))
    sz = box_sizes(boxes)
    size_mm = np.sqrt(np.abs(sz[:, 0] * sz[:, 1])) * depth / f
    size_mm = float(np.median(size_mm[agree])) if agree.any() else np.nan
    uv = project_rig(center[None, None, :], rig)[0, :, 0, :]  # (C, 2)
    for i in np.flatnonzero(~agree):
        half = 0.5 * size_mm * f[i] / depth[i] if depth[i] > 0 else np.nan
        boxes[i] = [uv[i, 0] - half, uv[i, 1] - half, uv[i, 0] + half, uv[i, 1] + half]
        scores[i] = 0.0


def detect_multiview_batch(
    frames: Sequence[Sequence[np.ndarray]],
    rig: CameraRig,
    source: BoxSource,
    config: ConsistencyConfig | None = None,
    valid: np.ndarray | None = None,
) -> list[MultiViewDetection]:
    """Consistent detections for several time instants.

    Args:
        frames: T lists of C BGR uint8 images (the rig's camera order).
        rig: the cameras.
        source: a :class:`~freipose.detect.base.BoxSource` (``Detector``,
            ``BackgroundSubtractor``, ``FixedBoxes``); all T*C images go through it at once.
        config: consistency settings (cube size etc.).
        valid: (T, C) bool, False where a frame could not be decoded: that image is not
            shown to ``source`` and the view has no candidate (default: all decoded).
    """
    c = len(rig)
    flat: list[np.ndarray] = []
    for t, fr in enumerate(frames):
        if len(fr) != c:
            raise ValueError(f"time instant {t}: expected {c} images ({rig.names}), got {len(fr)}")
        flat.extend(fr)
    if not flat:
        return []
    names = list(rig.names) * len(frames)
    if valid is None:
        cands = source.propose(flat, names)
    else:
        ok = np.asarray(valid, bool).reshape(-1)
        shown = [i for i in range(len(flat)) if ok[i]]
        found = iter(
            source.propose([flat[i] for i in shown], [names[i] for i in shown]) if shown else []
        )
        none = Candidates(np.zeros((0, 4)), np.zeros(0))
        cands = [next(found) if ok[i] else none for i in range(len(flat))]
    return [
        consistent_detection(cands[t * c : (t + 1) * c], rig, config) for t in range(len(frames))
    ]


def detect_multiview(
    frames_per_camera: Sequence[np.ndarray],
    rig: CameraRig,
    source: BoxSource,
    cube_size: float = 400.0,
    config: ConsistencyConfig | None = None,
) -> MultiViewDetection:
    """The consistent detection of one time instant: one image per camera of ``rig``.

    ``cube_size`` (mm) is used unless a full ``config`` is given.
    """
    cfg = config or ConsistencyConfig(cube_size=cube_size)
    return detect_multiview_batch([frames_per_camera], rig, source, cfg)[0]
