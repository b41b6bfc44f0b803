"""Soft skeleton constraints on smoothed poses: bone lengths near their median.

After the temporal smoother, the positions of every frame are moved to minimise

    sum (x - m)^2 / v  +  sum over bones ((|x_i - x_j| - L_b)^2 / s_b^2)

with ``m`` and ``v`` the smoother's posterior mean and variance per axis, ``L_b`` the median
length of bone ``b`` over the recording and ``s_b`` its robust spread (1.4826 x the median
absolute deviation, at least :data:`MIN_SPREAD_MM`): a soft penalty in the spirit of
Anipose's spatiotemporal filter, which pulls a bone that the recording shows to be rigid
firmly to its length and hardly touches one that varies (a limb across a joint). Bones
are the skeleton's limbs whose two ends are single keypoints. The problem is solved for
all frames at once by L-BFGS (``scipy.optimize``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from freipose.skeleton import Skeleton

MIN_SPREAD_MM = 0.5
_EPS = 1e-9


@dataclass(frozen=True)
class BoneFit:
    """Bone-constrained positions.

    Attributes:
        mean: (T, K, 3) positions in mm.
        pairs: (B, 2) keypoint indices of the bones.
        length: (B,) median length in mm.
        spread: (B,) robust spread of the length in mm (the penalty's scale).
    """

    mean: np.ndarray
    pairs: np.ndarray
    length: np.ndarray
    spread: np.ndarray


def bone_pairs(skeleton: Skeleton | None, keypoints: Sequence[str]) -> np.ndarray:
    """(B, 2) indices into ``keypoints`` of the skeleton's single-keypoint limbs."""
    if skeleton is None:
        return np.zeros((0, 2), np.int64)
    out = []
    for a, b in skeleton.limbs:
        if len(a) == 1 and len(b) == 1:
            na, nb = skeleton.keypoints[a[0]], skeleton.keypoints[b[0]]
            if na in keypoints and nb in keypoints:
                out.append((list(keypoints).index(na), list(keypoints).index(nb)))
    return np.array(out, np.int64).reshape(-1, 2)


def _lengths(x: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """(T, B) bone lengths of (T, K, 3) positions."""
    return np.linalg.norm(x[:, pairs[:, 0]] - x[:, pairs[:, 1]], axis=-1)


def constrain_bones(mean: np.ndarray, var: np.ndarray, pairs: np.ndarray) -> BoneFit:
    """Move (T, K, 3) ``mean`` (variance ``var``, mm^2) towards the median bone lengths.

    Args:
        mean: (T, K, 3) smoothed positions in mm (finite).
        var: (T, K, 3) their posterior variances in mm^2 (positive).
        pairs: (B, 2) keypoint indices of the bones (from :func:`bone_pairs`).

    Returns:
        The constrained positions with each bone's length and spread.
    """
    mean = np.asarray(mean, np.float64)
    w = 1.0 / np.maximum(np.asarray(var, np.float64), _EPS)
    lens = _lengths(mean, pairs)
    length = np.median(lens, axis=0)
    mad = np.median(np.abs(lens - length), axis=0)
    spread = np.maximum(1.4826 * mad, MIN_SPREAD_MM)
    if not len(pairs):
        return BoneFit(mean, pairs, length, spread)
    shape, i, j = mean.shape, pairs[:, 0], pairs[:, 1]
    wb = 1.0 / spread**2

    def cost(flat: np.ndarray) -> tuple[float, np.ndarray]:
        x = flat.reshape(shape)
        dx = x - mean
        d = x[:, i] - x[:, j]  # (T, B, 3)
        n = np.linalg.norm(d, axis=-1)
        r = n - length
        f = 0.5 * float((w * dx * dx).sum()) + 0.5 * float((wb * r * r).sum())
        g = w * dx
        gb = (wb * r / np.maximum(n, _EPS))[..., None] * d
        per_kp = g.transpose(1, 0, 2)  # (K, T, 3) view of g
        np.add.at(per_kp, i, gb.transpose(1, 0, 2))
        np.add.at(per_kp, j, -gb.transpose(1, 0, 2))
        return f, g.ravel()

    opt = minimize(cost, mean.ravel(), jac=True, method="L-BFGS-B", options={"maxiter": 500})
    return BoneFit(opt.x.reshape(shape), pairs, length, spread)
