"""The other animals painted out of an animal's views (``model.mask_others``).

With several animals, an animal's cube often holds parts of another one (a head beside its
flank, a paw over its back), and the network may place a keypoint on the other animal. With
``model.mask_others`` each view of an animal is shown with the other animals' bodies painted
a flat grey, except where they lie over this animal's own body (there the pixels stay, so
that no part of this animal is erased). A body is the convex hull of its projected
keypoints, widened by ``model.mask_radius`` mm.

The poses come from the labels during training (jittered like a network's, and sometimes
left out so the network also sees unpainted views) and, at inference, from a first pass
of the network over every animal (:func:`freipose.nn.evaluate.predict_dataset`,
``freipose predict --animals``).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import cv2
import numpy as np

from freipose.geometry.camera import CameraRig

log = logging.getLogger(__name__)

#: the grey the other animals are painted with (BGR uint8; 0 after the network's
#: normalisation ``BGR / 255 - 0.5``)
PAINT_VALUE = 128
#: share of training samples shown without painting (as the first inference pass sees them)
TRAIN_UNPAINTED = 0.25


def body_masks(
    rig: CameraRig,
    poses: np.ndarray,
    radius_mm: float,
    sizes: Sequence[tuple[int, int]],
) -> np.ndarray:
    """Where each animal's body is in each view: its keypoints' convex hull, widened.

    Args:
        rig: the V cameras.
        poses: (M, K, 3) world mm poses, NaN where unknown.
        radius_mm: half-width of the body around its keypoints.
        sizes: per view the image's (width, height).

    Returns:
        (M, V) list of (H, W) bool masks as an object array.
    """
    poses = np.asarray(poses, np.float64)
    poses = poses.reshape(-1, poses.shape[-2], 3)
    m_n, k_n = poses.shape[:2]
    out = np.empty((m_n, len(rig)), dtype=object)
    flat = np.nan_to_num(poses.reshape(-1, 3), nan=0.0)
    uv_all = rig.project(flat).reshape(len(rig), m_n, k_n, 2)
    uv_all[:, ~np.isfinite(poses).all(-1)] = np.nan
    for v, cam in enumerate(rig):
        w, h = sizes[v]
        depth = poses @ cam.R[2] + cam.t[2]  # (M, K)
        uv = uv_all[v]
        f = float(np.sqrt(abs(cam.K[0, 0] * cam.K[1, 1])))
        for m in range(len(poses)):
            mask = np.zeros((h, w), np.uint8)
            ok = np.isfinite(uv[m]).all(-1) & (np.nan_to_num(depth[m]) > 1.0)
            if ok.any():
                pts = np.round(uv[m][ok]).astype(np.int64)
                rad = np.clip(radius_mm * f / depth[m][ok], 1.0, max(w, h))
                near = (np.abs(pts) < 4 * max(w, h)).all(-1)  # cv2 draws in int32
                pts, rad = pts[near], rad[near]
                if len(pts) >= 3:
                    hull = cv2.convexHull(pts.astype(np.int32))
                    cv2.fillConvexPoly(mask, hull, 1)
                    # the hull widened by the body's half-width along its edges
                    cv2.polylines(mask, [hull], True, 1, max(1, int(round(2 * rad.mean()))))
                for (x, y), r in zip(pts, rad, strict=True):
                    cv2.circle(mask, (int(x), int(y)), int(round(r)), 1, -1)
            out[m, v] = mask.astype(bool)
    return out


def paint_other_animals(
    images: Sequence[np.ndarray],
    rig: CameraRig,
    own: np.ndarray | None,
    others: np.ndarray,
    radius_mm: float,
) -> list[np.ndarray]:
    """The views with the other animals' bodies painted grey, except over this animal's.

    Args:
        images: V BGR uint8 (H, W, 3) full frames of ``rig``'s cameras (not modified).
        rig: the V cameras.
        own: (K, 3) this animal's pose in mm (None or all NaN: nothing is kept).
        others: (M, K, 3) the other animals' poses in mm (NaN where unknown).
        radius_mm: half-width of a body around its keypoints.

    Returns:
        V images; a view with nothing to paint is the input array itself, a painted one a copy.
    """
    others = np.asarray(others, np.float64)
    if others.size == 0 or not np.isfinite(others).any() or not images:
        return list(images)
    sizes = [(int(im.shape[1]), int(im.shape[0])) for im in images]
    theirs = body_masks(rig, others, radius_mm, sizes)
    mine = None
    if own is not None and np.isfinite(own).any():
        mine = body_masks(rig, np.asarray(own)[None], radius_mm, sizes)[0]
    out = []
    for v, im in enumerate(images):
        paint = np.logical_or.reduce(list(theirs[:, v]))
        if mine is not None:
            paint &= ~mine[v]
        if paint.any():
            im = im.copy()
            im[paint] = PAINT_VALUE
        out.append(im)
    return out


def warn_if_one_animal(mask_others: bool, individuals: Sequence[str]) -> None:
    """Log a warning when ``mask_others`` is set but the training labels hold one animal."""
    if mask_others and len(individuals) < 2:
        log.warning(
            "model.mask_others is set, but the training labels hold one animal per instant "
            "(no `individual` column with two or more animals): nothing is painted; label "
            "several animals per instant (freipose label --animals, or labels imported from "
            "multi-animal SLEAP / DeepLabCut) or leave mask_others out"
        )
