"""Axis-aligned boxes ``(x0, y0, x1, y1)`` in full-image pixels: making, comparing, clipping.

Boxes use the same continuous coordinates as :mod:`freipose.geometry.crops` (pixel
centres at integer coordinates, so an image of width ``W`` spans ``-0.5 .. W - 0.5``).
A missing box is all NaN.
"""

from __future__ import annotations

import warnings

import numpy as np


def boxes_from_points(
    points2d: np.ndarray, margin: float = 0.1, min_points: int = 2, min_size: float = 4.0
) -> np.ndarray:
    """The bounding boxes of 2D points, widened by a relative margin.

    Args:
        points2d: (..., K, 2) pixels, NaN where a point is missing.
        margin: added on every side, as a fraction of the longer box side.
        min_points: fewest finite points for a box; fewer gives a NaN box.
        min_size: the smallest box side in pixels (tiny boxes are grown about their centre).

    Returns:
        (..., 4) boxes ``(x0, y0, x1, y1)``; NaN where too few points.
    """
    p = np.asarray(points2d, dtype=np.float64)
    if p.ndim < 2 or p.shape[-1] != 2:
        raise ValueError(f"points2d must have shape (..., K, 2), got {p.shape}")
    ok = np.isfinite(p).all(-1)
    n = ok.sum(-1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices give NaN boxes
        lo = np.nanmin(np.where(ok[..., None], p, np.nan), axis=-2)
        hi = np.nanmax(np.where(ok[..., None], p, np.nan), axis=-2)
    side = np.maximum(np.max(hi - lo, axis=-1), 0.0)
    pad = margin * side
    lo = lo - pad[..., None]
    hi = hi + pad[..., None]
    c = (lo + hi) / 2
    half = np.maximum((hi - lo) / 2, min_size / 2)
    out = np.concatenate([c - half, c + half], axis=-1)
    out[n < min_points] = np.nan
    return out


def box_centers(boxes: np.ndarray) -> np.ndarray:
    """Centres (..., 2) of boxes (..., 4)."""
    b = np.asarray(boxes, dtype=np.float64)
    return np.stack([(b[..., 0] + b[..., 2]) / 2, (b[..., 1] + b[..., 3]) / 2], axis=-1)


def box_sizes(boxes: np.ndarray) -> np.ndarray:
    """Widths and heights (..., 2) of boxes (..., 4)."""
    b = np.asarray(boxes, dtype=np.float64)
    return np.stack([b[..., 2] - b[..., 0], b[..., 3] - b[..., 1]], axis=-1)


def box_area(boxes: np.ndarray) -> np.ndarray:
    """Areas (...,) of boxes (..., 4); 0 for empty boxes, NaN for missing ones."""
    s = box_sizes(boxes)
    return np.clip(s[..., 0], 0, None) * np.clip(s[..., 1], 0, None)


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Intersection over union of boxes a (..., 4) and b (..., 4) (broadcast); NaN if missing."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    x0 = np.maximum(a[..., 0], b[..., 0])
    y0 = np.maximum(a[..., 1], b[..., 1])
    x1 = np.minimum(a[..., 2], b[..., 2])
    y1 = np.minimum(a[..., 3], b[..., 3])
    inter = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    union = box_area(a) + box_area(b) - inter
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(union > 0, inter / union, 0.0) * np.where(
            np.isfinite(inter) & np.isfinite(union), 1.0, np.nan
        )


def clip_boxes(boxes: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Boxes (..., 4) clipped to an image of ``size`` = (width, height)."""
    b = np.array(boxes, dtype=np.float64, copy=True)
    w, h = size
    b[..., [0, 2]] = np.clip(b[..., [0, 2]], -0.5, w - 0.5)
    b[..., [1, 3]] = np.clip(b[..., [1, 3]], -0.5, h - 0.5)
    return b


def visible_fraction(boxes: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """The fraction (...,) of each box's area inside an image of ``size`` = (w, h).

    0 for empty boxes, NaN for missing ones.
    """
    full = box_area(boxes)
    inside = box_area(clip_boxes(boxes, size))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(full > 0, inside / full, 0.0) * np.where(np.isfinite(full), 1.0, np.nan)


def transform_boxes(boxes: np.ndarray, A: np.ndarray) -> np.ndarray:
    """The axis-aligned boxes (..., 4) enclosing affinely mapped boxes; ``A`` is 2x3 or 3x3.

    ``A`` maps pixel centres (OpenCV's ``warpAffine`` convention); box edges are mapped as
    points, which is exact for scalings, translations and flips.
    """
    b = np.asarray(boxes, dtype=np.float64)
    M = np.asarray(A, dtype=np.float64)[:2]
    xs = b[..., [0, 2, 0, 2]]
    ys = b[..., [1, 1, 3, 3]]
    u = M[0, 0] * xs + M[0, 1] * ys + M[0, 2]
    v = M[1, 0] * xs + M[1, 1] * ys + M[1, 2]
    return np.stack([u.min(-1), v.min(-1), u.max(-1), v.max(-1)], axis=-1)


def nms(boxes: np.ndarray, scores: np.ndarray, iou_threshold: float = 0.5) -> np.ndarray:
    """Greedy non-maximum suppression; returns the kept indices, best score first."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    s = np.asarray(scores, dtype=np.float64).reshape(-1)
    order = np.argsort(-s, kind="stable")
    keep: list[int] = []
    for i in order:
        if not np.isfinite(s[i]) or not np.isfinite(b[i]).all():
            continue
        if keep and np.any(box_iou(b[keep], b[i]) > iou_threshold):
            continue
        keep.append(int(i))
    return np.asarray(keep, dtype=np.int64)
