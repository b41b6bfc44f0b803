"""Several animals: boxes of every animal in every view, grouped into 3D animal hypotheses.

* :class:`SplitForeground` (a :class:`~freipose.detect.base.BoxSource`): background
  subtraction (the foreground of a fitted
  :class:`~freipose.detect.fallback.BackgroundSubtractor`, without its thin parts such as
  tails, which would stretch a box far past the body) that proposes one box per
  animal: fragments of one animal are merged (a smaller gap than the single-animal
  path, so that nearby animals stay apart), and a blob larger than one animal is split
  into as many animals as its area holds (the expected count shared out by area): first
  by eroding it (the distance transform's cores) until it falls into that many parts,
  which separates animals touching at a narrow contact; where no erosion separates them
  (animals pressed together side by side), by k-means on the blob's pixels;
* :class:`PeakBoxes` wraps any box source (e.g. the trained
  :class:`~freipose.detect.detector.Detector`, whose candidates are the peaks of its heat
  map; load it with ``top_k`` >= animals + 2) and keeps up to ``max_boxes`` candidates
  per view above ``min_score`` after non-maximum suppression;
* :func:`detect_animals` groups the boxes of all views into 3D animal hypotheses
  (:func:`freipose.geometry.association.associate` on box centres, with tolerances and a
  3D size check from the box sizes) and gives per animal a box in every view: its own
  box where the view agreed, else a box of the view that lies on the animal's projection
  (*shared*: the view shows two animals as one blob), else a replacement box of the
  animal's size at the projected centre (score 0), and the cube crops of the pose network.

The single-animal path (:mod:`.multiview`) is separate and unchanged.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from freipose.detect.base import BoxSource, Candidates, DetectConfigError
from freipose.detect.boxes import box_centers, box_sizes, nms
from freipose.detect.fallback import BackgroundSubtractor, _merged_blobs
from freipose.geometry import CameraRig, project_rig
from freipose.geometry.association import Association, AssociationConfig, associate
from freipose.geometry.crops import cube_crop_boxes

CORE_LEVELS = (0.3, 0.45, 0.6, 0.75)  # erosion depths tried, fractions of the deepest pixel


def _shares(areas: np.ndarray, n_animals: int, ratio: float = 1.75) -> np.ndarray:
    """How many animals each blob holds: (n,) ints >= 1, summing to at most ``n_animals``.

    Extra animals go one by one to the blob with the largest area per animal, while that
    area is at least ``ratio`` x the largest area per animal of the other blobs (one
    animal's size); a lone blob takes them all.
    """
    k = np.ones(len(areas), dtype=np.int64)
    while len(areas) and k.sum() < n_animals:
        per = np.asarray(areas, dtype=np.float64) / k
        i = int(np.argmax(per))
        others = np.delete(per, i)
        if len(others) and per[i] < ratio * others.max():
            break
        k[i] += 1
    return k


def without_thin_parts(mask: np.ndarray, thin: float) -> np.ndarray:
    """The foreground without its thin parts (a rat's tail, a shadow's edge).

    An opening with a disc of radius ``thin`` x the half-width of the thickest blob (its
    deepest distance-transform pixel) removes every part narrower than the disc; the
    bodies keep their outline. Where the opening would remove more than half the
    foreground (no animal is that thin), the mask is returned as it is.

    Args:
        mask: (h, w) uint8 0/255 foreground.
        thin: the disc's radius as a fraction of the thickest half-width (0: no change).

    Returns:
        (h, w) uint8 0/255.
    """
    m = np.asarray(mask, np.uint8)
    if thin <= 0 or not m.any():
        return m
    dt = cv2.distanceTransform((m > 0).astype(np.uint8), cv2.DIST_L2, 3)
    r = int(round(thin * float(dt.max())))
    if r < 1:
        return m
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    opened = cv2.morphologyEx(m, cv2.MORPH_OPEN, disc)
    return opened if 2 * np.count_nonzero(opened) >= np.count_nonzero(m) else m


def _seeds_on(blob: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """The seeds (n, 2) (x, y in the blob's pixels) that lie on the blob, finite ones only."""
    sd = seeds[np.isfinite(seeds).all(-1)]
    h, w = blob.shape
    ix, iy = np.round(sd[:, 0]).astype(int), np.round(sd[:, 1]).astype(int)
    ok = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
    ok[ok] = blob[iy[ok], ix[ok]]
    return sd[ok]


def split_by_seeds(mask: np.ndarray, seeds: np.ndarray) -> list[np.ndarray]:
    """Split a blob between animals whose centres are known: each pixel to its nearest seed.

    Args:
        mask: (h, w) bool, the blob.
        seeds: (k, 2) the animals' centres, x and y in the blob's pixels.

    Returns:
        k bool masks (h, w).
    """
    ys, xs = np.nonzero(mask)
    d = np.hypot(xs[:, None] - seeds[None, :, 0], ys[:, None] - seeds[None, :, 1])
    near = np.argmin(d, axis=1)
    out = []
    for j in range(len(seeds)):
        part = np.zeros(mask.shape, bool)
        part[ys[near == j], xs[near == j]] = True
        out.append(part)
    return out


def split_blob(
    mask: np.ndarray, k: int, colour: np.ndarray | None = None, seed: int = 0
) -> list[np.ndarray]:
    """Split one blob into ``k`` animals.

    Args:
        mask: (h, w) bool, the blob.
        k: how many animals it holds.
        colour: (h, w, 3) the image under the blob, used by the k-means fallback.
        seed: k-means seed.

    Returns:
        k bool masks (h, w) (fewer when the blob has fewer than k pixels).
    """
    m = np.asarray(mask, bool)
    if k <= 1 or m.sum() < k:
        return [m]
    dt = cv2.distanceTransform(m.astype(np.uint8), cv2.DIST_L2, 3)
    for level in CORE_LEVELS:
        core = dt > level * dt.max()
        n, lab, stats, _ = cv2.connectedComponentsWithStats(core.astype(np.uint8), connectivity=8)
        area = stats[1:, cv2.CC_STAT_AREA]
        big = np.flatnonzero(area >= 0.15 * area.sum() / k) + 1
        if len(big) >= k:
            keep = big[np.argsort(-area[big - 1])][:k]
            seeds = np.isin(lab, keep)
            _, (iy, ix) = ndimage.distance_transform_edt(~seeds, return_indices=True)
            owner = lab[iy, ix]
            return [m & (owner == j) for j in keep]
    ys, xs = np.nonzero(m)
    feats = np.stack([xs, ys], 1).astype(np.float32)
    if colour is not None:
        spread = float(max(np.ptp(xs), np.ptp(ys), 1))
        c = np.asarray(colour, np.float32)[ys, xs] / 255.0
        feats = np.concatenate([feats, c * 0.5 * spread], 1)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.5)
    cv2.setRNGSeed(seed)
    _, lab1, _ = cv2.kmeans(feats, k, None, crit, 3, cv2.KMEANS_PP_CENTERS)
    out = []
    for j in range(k):
        part = np.zeros_like(m)
        part[ys[lab1[:, 0] == j], xs[lab1[:, 0] == j]] = True
        out.append(part)
    return out


class SplitForeground:
    """Background subtraction with one box per animal (a :class:`BoxSource`).

    Args:
        subtractor: a fitted :class:`BackgroundSubtractor` (its backgrounds, threshold
            and work size).
        n_animals: how many animals the arena holds (the most boxes per view).
        merge_gap: fragments closer than this fraction of a group's longer side merge.
        min_area: smallest animal, as a fraction of the image area.
        margin: added on every side of a box, as a fraction of its longer side.
        thin: parts of the foreground narrower than about this fraction of the thickest
            animal's width (tails, their shadows) are removed before the boxes are made
            (:func:`without_thin_parts`); 0 keeps them.
    """

    def __init__(
        self,
        subtractor: BackgroundSubtractor,
        n_animals: int,
        merge_gap: float = 0.05,
        min_area: float | None = None,
        margin: float | None = None,
        thin: float = 0.3,
    ):
        if n_animals < 1:
            raise DetectConfigError(f"n_animals must be >= 1, got {n_animals}")
        self.subtractor = subtractor
        self.n_animals = int(n_animals)
        self.merge_gap = merge_gap
        self.min_area = subtractor.min_area if min_area is None else min_area
        self.margin = subtractor.margin if margin is None else margin
        self.thin = thin

    def _one(self, image: np.ndarray, camera: str, seeds: np.ndarray | None = None) -> Candidates:
        mask, s = self.subtractor.foreground(image, camera)
        mask = without_thin_parts(mask, self.thin)
        n, lab, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        groups, areas = _merged_blobs(stats[1:], self.min_area * mask.size, self.merge_gap)
        groups, areas = groups[: self.n_animals], areas[: self.n_animals]
        if len(groups) == 0:
            return Candidates.empty()
        small = None
        if s < 1:
            h, w = mask.shape
            small = cv2.resize(np.asarray(image), (w, h), interpolation=cv2.INTER_AREA)
        boxes, sizes = [], []
        for box, k in zip(groups, _shares(areas, self.n_animals), strict=True):
            x0, y0 = (int(v) for v in np.floor(box[:2] + 0.5))
            x1, y1 = (int(v) for v in np.ceil(box[2:] + 0.5))
            blob = mask[y0:y1, x0:x1] > 0
            img = (small if small is not None else np.asarray(image))[y0:y1, x0:x1]
            inner = None if seeds is None else _seeds_on(blob, (seeds + 0.5) * s - 0.5 - [x0, y0])
            if k > 1 and inner is not None and len(inner) >= k:
                parts = split_by_seeds(blob, inner[:k])
            else:
                parts = split_blob(blob, int(k), img if img.ndim == 3 else None)
            for part in parts:
                ys, xs = np.nonzero(part)
                if len(xs) == 0:
                    continue
                boxes.append([xs.min() + x0 - 0.5, ys.min() + y0 - 0.5,
                              xs.max() + x0 + 0.5, ys.max() + y0 + 0.5])  # fmt: skip
                sizes.append(len(xs))
        b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
        side = np.maximum(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1])
        b = b + (self.margin * side)[:, None] * np.array([-1, -1, 1, 1])
        b = (b + 0.5) / s - 0.5  # back to full-image pixels
        a = np.asarray(sizes, dtype=np.float64)
        return Candidates(b, a / a.max()) if len(a) else Candidates.empty()

    def propose(self, images: Sequence[np.ndarray], cameras: Sequence[str]) -> list[Candidates]:
        """Up to ``n_animals`` boxes per image (full-image pixels), score = area / largest."""
        if len(images) != len(cameras):
            raise ValueError(f"{len(images)} images but {len(cameras)} camera names")
        return [self._one(img, cam) for img, cam in zip(images, cameras, strict=True)]

    def propose_seeded(
        self, images: Sequence[np.ndarray], cameras: Sequence[str], seeds: Sequence[np.ndarray]
    ) -> list[Candidates]:
        """:meth:`propose`, blobs of several animals split at their expected centres.

        ``seeds`` holds per image the centres (n, 2) in full-image pixels (e.g. the
        projections of the 3D hypotheses); a blob of k animals on which at least k of
        them lie is split between the first k (:func:`split_by_seeds`), other blobs as
        in :meth:`propose`.
        """
        if not len(images) == len(cameras) == len(seeds):
            raise ValueError(f"{len(images)} images, {len(cameras)} camera names and "
                             f"{len(seeds)} seed arrays")  # fmt: skip
        return [self._one(img, cam, np.asarray(sd, np.float64).reshape(-1, 2))
                for img, cam, sd in zip(images, cameras, seeds, strict=True)]  # fmt: skip

    def foreground_masks(
        self, images: Sequence[np.ndarray], cameras: Sequence[str]
    ) -> list[np.ndarray]:
        """The foreground the boxes are made from: (H, W) bool per image, full size."""
        if len(images) != len(cameras):
            raise ValueError(f"{len(images)} images but {len(cameras)} camera names")
        out = []
        for img, cam in zip(images, cameras, strict=True):
            mask, _ = self.subtractor.foreground(img, cam)
            mask = without_thin_parts(mask, self.thin)
            h, w = np.asarray(img).shape[:2]
            if mask.shape != (h, w):
                mask = cv2.resize(mask, (w, h), interpolation=cv2.INTER_NEAREST)
            out.append(mask > 0)
        return out


class PeakBoxes:
    """Up to ``max_boxes`` non-overlapping candidates per view from any box source.

    Args:
        source: the box source (``propose(images, cameras)``), e.g. a ``Detector`` loaded
            with ``top_k`` at least ``max_boxes``.
        max_boxes: most boxes per view (animals plus a margin for false boxes).
        min_score: lowest score kept.
        iou_threshold: boxes overlapping a better one by more than this are dropped
            (high, since touching animals overlap).
    """

    def __init__(
        self, source: BoxSource, max_boxes: int, min_score: float = 0.1, iou_threshold: float = 0.7
    ):
        if max_boxes < 1:
            raise DetectConfigError(f"max_boxes must be >= 1, got {max_boxes}")
        self.source = source
        self.max_boxes = int(max_boxes)
        self.min_score = float(min_score)
        self.iou_threshold = float(iou_threshold)

    def propose(self, images: Sequence[np.ndarray], cameras: Sequence[str]) -> list[Candidates]:
        """The source's candidates after the score threshold and non-maximum suppression."""
        out = []
        for cd in self.source.propose(images, cameras):
            ok = cd.scores >= self.min_score
            b, s = cd.boxes[ok], cd.scores[ok]
            keep = nms(b, s, self.iou_threshold)[: self.max_boxes]
            out.append(Candidates(b[keep], s[keep]))
        return out


@dataclass(frozen=True)
class AnimalsConfig:
    """Settings of :func:`detect_animals`.

    Attributes:
        cube_size: edge of the pose network's cube around each animal, mm.
        min_score: lowest box score used.
        max_boxes: most boxes per view used (best first).
        rel_tolerance: a box centre agrees within this fraction of ``sqrt(w * h)`` ...
        min_tolerance_px: ... and at least this many pixels.
        min_views: fewest views of an animal hypothesis (>= 2).
        max_size_ratio: largest ratio of the animal's sizes in mm seen from two views.
        max_animals: most hypotheses per time instant (None: as many as agree).
    """

    cube_size: float = 400.0
    min_score: float = 0.1
    max_boxes: int = 8
    rel_tolerance: float = 0.25
    min_tolerance_px: float = 8.0
    min_views: int = 2
    max_size_ratio: float = 2.0
    max_animals: int | None = None

    def __post_init__(self) -> None:
        if not self.cube_size > 0:
            raise DetectConfigError(f"cube_size must be positive (mm), got {self.cube_size}")
        if self.max_boxes < 1:
            raise DetectConfigError(f"max_boxes must be >= 1, got {self.max_boxes}")
        if self.min_views < 2:
            raise DetectConfigError(
                f"min_views must be >= 2 (a 3D point needs two views), got {self.min_views}"
            )
        if self.rel_tolerance < 0 or self.min_tolerance_px <= 0:
            raise DetectConfigError("rel_tolerance must be >= 0 and min_tolerance_px > 0")


@dataclass(frozen=True, eq=False)
class AnimalDetections:
    """The animals found at one time instant over C cameras (H hypotheses).

    Attributes:
        centers: (H, 3) world mm.
        boxes: (H, C, 4) per animal and view: its own box, a shared box or a replacement.
        scores: (H, C) the box's score; 0 for replacement boxes.
        own: (H, C) the view's box belongs to this animal alone (the view agreed).
        members: (H, C) int64 index of the own box in the view's candidates, -1 none.
        shared: (H, C) the view's box was taken by another animal and lies on this one
            (two animals seen as one blob).
        n_views: (H,) views that agreed.
        sizes_mm: (H,) the animal's size in mm seen from its views.
        crop_boxes: (H, C, 4) square boxes around the projected cube.
        leftover: (C,) per view the boxes (n, 4) of no animal (false detections).
    """

    centers: np.ndarray
    boxes: np.ndarray
    scores: np.ndarray
    own: np.ndarray
    members: np.ndarray
    shared: np.ndarray
    n_views: np.ndarray
    sizes_mm: np.ndarray
    crop_boxes: np.ndarray
    leftover: tuple[np.ndarray, ...]

    def __len__(self) -> int:
        return len(self.centers)


def _views(cands: Sequence[Candidates], cfg: AnimalsConfig) -> tuple[list[np.ndarray], ...]:
    """Per view the boxes, scores, centres, tolerances, sizes and candidate indices used."""
    boxes, scores, centres, tols, sizes, index = [], [], [], [], [], []
    for cd in cands:
        ok = (cd.scores >= cfg.min_score) & np.isfinite(cd.boxes).all(-1)
        idx = np.flatnonzero(ok)[: cfg.max_boxes]
        index.append(idx)
        b, s = cd.boxes[idx], cd.scores[idx]
        sz = np.sqrt(np.abs(np.prod(box_sizes(b), -1)))
        boxes.append(b)
        scores.append(s)
        centres.append(box_centers(b))
        tols.append(np.maximum(cfg.min_tolerance_px, cfg.rel_tolerance * sz))
        sizes.append(sz)
    return boxes, scores, centres, tols, sizes, index


def _fill_views(
    a: Association,
    rig: CameraRig,
    boxes: list[np.ndarray],
    scores: list[np.ndarray],
    tols: list[np.ndarray],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boxes (H, C, 4), scores (H, C) and shared (H, C) of every animal in every view."""
    h, c = a.members.shape
    out = np.full((h, c, 4), np.nan)
    sc = np.zeros((h, c))
    shared = np.zeros((h, c), bool)
    uv = project_rig(a.points[:, None, :], rig)[:, :, 0, :] if h else np.zeros((0, c, 2))
    depth = np.einsum("cij,hj->hci", rig.R, a.points)[..., 2] + rig.t[None, :, 2]
    f = np.sqrt(np.abs(rig.K[:, 0, 0] * rig.K[:, 1, 1]))
    for i in range(h):
        for v in range(c):
            m = a.members[i, v]
            if m >= 0:
                out[i, v], sc[i, v] = boxes[v][m], scores[v][m]
                continue
            if len(boxes[v]):
                d = np.linalg.norm(box_centers(boxes[v]) - uv[i, v], axis=-1) / tols[v]
                j = int(np.argmin(d))
                if d[j] < 1.0:  # the box of another animal covers this one: shared
                    out[i, v], sc[i, v], shared[i, v] = boxes[v][j], scores[v][j], True
                    continue
            half = 0.5 * a.sizes_mm[i] * f[v] / depth[i, v] if depth[i, v] > 0 else np.nan
            out[i, v] = [uv[i, v, 0] - half, uv[i, v, 1] - half,
                         uv[i, v, 0] + half, uv[i, v, 1] + half]  # fmt: skip
    return out, sc, shared


def detect_animals(
    candidates: Sequence[Candidates],
    rig: CameraRig,
    config: AnimalsConfig | None = None,
    bounds: np.ndarray | None = None,
) -> AnimalDetections:
    """The animals of one time instant: 3D hypotheses with a box in every view.

    Args:
        candidates: one :class:`Candidates` per camera of ``rig`` (same order), several
            animals' boxes each.
        rig: the cameras (C).
        config: tolerances, limits, cube size.
        bounds: (3, 2) world box mm the animals' centres lie in (e.g. the arena).

    Returns:
        :class:`AnimalDetections`, the animals seen by most views first.
    """
    cfg = config or AnimalsConfig()
    if len(candidates) != len(rig):
        raise ValueError(
            f"expected candidates for {len(rig)} cameras ({rig.names}), got {len(candidates)}"
        )
    boxes, scores, centres, tols, sizes, index = _views(candidates, cfg)
    acfg = AssociationConfig(
        min_views=cfg.min_views, max_size_ratio=cfg.max_size_ratio,
        max_hypotheses=cfg.max_animals,
    )  # fmt: skip
    a = associate(centres, rig, tols, sizes, scores, acfg, bounds)
    out, sc, shared = _fill_views(a, rig, boxes, scores, tols)
    crops = cube_crop_boxes(rig, a.points, cfg.cube_size).reshape(len(a), len(rig), 4)
    return AnimalDetections(
        centers=a.points,
        boxes=out,
        scores=sc,
        own=a.members >= 0,
        members=np.stack(
            [
                np.where(a.members[:, v] >= 0, index[v][np.maximum(a.members[:, v], 0)], -1)
                if len(index[v])
                else np.full(len(a), -1)
                for v in range(len(rig))
            ],
            axis=1,
        ).reshape(len(a), len(rig)),  # fmt: skip
        shared=shared,
        n_views=a.n_views,
        sizes_mm=a.sizes_mm,
        crop_boxes=crops,
        leftover=tuple(boxes[v][a.leftover[v]] for v in range(len(rig))),
    )


def detect_animals_batch(
    frames: Sequence[Sequence[np.ndarray]],
    rig: CameraRig,
    source: BoxSource,
    config: AnimalsConfig | None = None,
    bounds: np.ndarray | None = None,
) -> list[AnimalDetections]:
    """:func:`detect_animals` for T time instants of C images each (the rig's order).

    All T*C images go through ``source`` (e.g. :class:`SplitForeground`,
    :class:`PeakBoxes`) at once.
    """
    c = len(rig)
    flat: list[np.ndarray] = []
    for t, fr in enumerate(frames):
        if len(fr) != c:
            raise ValueError(f"time instant {t}: expected {c} images ({rig.names}), got {len(fr)}")
        flat.extend(fr)
    if not flat:
        return []
    cands = source.propose(flat, list(rig.names) * len(frames))
    return [
        detect_animals(cands[t * c : (t + 1) * c], rig, config, bounds) for t in range(len(frames))
    ]
