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
    """Proposals X (T, H, 3) against T instants' candidates (T, C, M, ...).

    Returns per proposal and view the agreement (T, H, C) and best candidate (T, H, C), and
    the quality (T, H).
    """
    uv = project_rig(X[:, :, None, :], rig)[:, :, :, 0, :]  # (T, H, C, 2), NaN behind a camera
    err = np.linalg.norm(uv[:, :, :, None, :] - centres[:, None], axis=-1)  # (T, H, C, M)
    tol, sc = tol[:, None], np.nan_to_num(scores, nan=0.0)[:, None]
    inl = np.isfinite(err) & (err < tol)
    rank = np.where(inl, err / tol / np.sqrt(sc + 1e-3), np.inf)
    best = np.argmin(rank, axis=-1)  # (T, H, C)
    agree = inl.any(-1)
    gain = np.where(inl, sc * (1 - err / tol), 0.0).max(-1)
    return agree, best, gain.sum(-1)


def _proposals(centres: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """(T, H, C, 2) observations: every pair of views and of their candidates' centres.

    The proposals are laid out in the same order for every instant (view pairs, then
    candidate pairs); a proposal with a missing candidate is all NaN.
    """
    T, c, m = scores.shape
    combos = [(i, j, a, b) for i, j in itertools.combinations(range(c), 2)
              for a, b in itertools.product(range(m), range(m))]  # fmt: skip
    obs = np.full((T, len(combos), c, 2), np.nan)
    for h, (i, j, a, b) in enumerate(combos):
        ok = np.isfinite(scores[:, i, a]) & np.isfinite(scores[:, j, b])
        obs[ok, h, i] = centres[ok, i, a]
        obs[ok, h, j] = centres[ok, j, b]
    return obs


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
    return consistent_detections([candidates], rig, config)[0]


def consistent_detections(
    candidates: Sequence[Sequence[Candidates]],
    rig: CameraRig,
    config: ConsistencyConfig | None = None,
) -> list[MultiViewDetection]:
    """:func:`consistent_detection` of T time instants, computed together.

    Args:
        candidates: per instant, one :class:`Candidates` per camera of ``rig``.
        rig: the cameras (C).
        config: tolerances, cube size, etc.

    Returns:
        T :class:`MultiViewDetection`.
    """
    cfg = config or ConsistencyConfig()
    c = len(rig)
    for cands in candidates:
        if len(cands) != c:
            raise ValueError(f"expected candidates for {c} cameras ({rig.names}), got {len(cands)}")
    if not candidates:
        return []
    padded = [_padded(cands, cfg) for cands in candidates]
    boxes = np.stack([p[0] for p in padded])  # (T, C, M, 4)
    scores = np.stack([p[1] for p in padded])  # (T, C, M)
    centres = box_centers(boxes)  # (T, C, M, 2)
    sz = box_sizes(boxes)
    tol = np.maximum(
        cfg.min_tolerance_px, cfg.rel_tolerance * np.sqrt(np.abs(sz[..., 0] * sz[..., 1]))
    )
    tol = np.where(np.isfinite(scores), tol, np.nan)
    center, agree, chosen = _centres(centres, scores, tol, rig, cfg)
    crops = cube_crop_boxes(rig, center, cfg.cube_size)  # (T, C, 4)
    return [
        _detection(cands, boxes[k], scores[k], center[k], agree[k], chosen[k], crops[k], rig)
        for k, cands in enumerate(candidates)
    ]


def _centres(
    centres: np.ndarray,
    scores: np.ndarray,
    tol: np.ndarray,
    rig: CameraRig,
    cfg: ConsistencyConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steps 1-4 of the module docstring for T instants.

    Returns:
        ``(center, agree, chosen)``: (T, 3) world mm (NaN: none), (T, C) agreeing views and
        (T, C) their chosen candidates.
    """
    T, c = scores.shape[:2]
    idx = np.arange(c)
    center = np.full((T, 3), np.nan)
    agree = np.zeros((T, c), dtype=bool)
    chosen = np.zeros((T, c), dtype=np.int64)
    # 1. Proposals from every pair of views and every pair of their candidates.
    X = triangulate(_proposals(centres, scores), rig)  # (T, H, 3)
    found = np.isfinite(X).all(-1)
    # 2-3. Verify every proposal; most agreeing views, then best quality (the last of ties).
    ag, best, quality = _verify(np.where(found[..., None], X, np.nan), rig, centres, scores, tol)
    count = np.where(found, ag.sum(-1), -1)
    top = np.zeros(T, dtype=np.int64)
    for k in range(T):
        cand = np.flatnonzero(found[k])
        if len(cand):
            top[k] = cand[np.lexsort((quality[k, cand], count[k, cand]))[-1]]
    rows = np.arange(T)
    won = found.any(-1) & (count[rows, top] >= cfg.min_views)
    agree[won], chosen[won] = ag[rows, top][won], best[rows, top][won]
    # 4. Refit from the chosen boxes, then verify and refit once more. The weighted DLT
    # suffices: box centres are not projections of one 3D point, so a pixel-optimal polish
    # of their triangulation gains nothing. An instant stops at its first failed round.
    active = won.copy()
    for _ in range(2):
        pts = np.where(agree[..., None], centres[rows[:, None], idx, chosen], np.nan)
        w = np.where(agree, scores[rows[:, None], idx, chosen], 0.0)
        Xr = triangulate_weighted(pts, np.maximum(w, 1e-3) * agree, rig)  # (T, 3)
        active &= np.isfinite(Xr).all(-1)
        ag2, best2, _ = _verify(Xr[:, None], rig, centres, scores, tol)
        active &= ag2[:, 0].sum(-1) >= cfg.min_views
        center[active], agree[active], chosen[active] = (
            Xr[active],
            ag2[active, 0],
            best2[active, 0],
        )
    unrefined = won & ~np.isfinite(center).all(-1)
    center[unrefined] = X[rows, top][unrefined]
    return center, agree, chosen


def _detection(
    candidates: Sequence[Candidates],
    boxes: np.ndarray,
    scores: np.ndarray,
    center: np.ndarray,
    agree: np.ndarray,
    chosen: np.ndarray,
    crops: np.ndarray,
    rig: CameraRig,
) -> MultiViewDetection:
    """Step 5 of the module docstring: one instant's boxes around its centre."""
    c = len(rig)
    out_boxes = np.full((c, 4), np.nan)
    out_scores = np.full(c, np.nan)
    if np.isfinite(center).all():
        idx = np.arange(c)
        out_boxes[agree] = boxes[idx, chosen][agree]
        out_scores[agree] = scores[idx, chosen][agree]
        _replace_missing(out_boxes, out_scores, agree, center, rig)
    else:
        agree = np.zeros(c, dtype=bool)
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
    return consistent_detections([cands[t * c : (t + 1) * c] for t in range(len(frames))],
                                 rig, config)  # fmt: skip


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
