"""Robust losses and detection-noise estimates of the bundle adjustment.

The losses are those of ``scipy.optimize.least_squares`` (``linear``, ``huber``,
``soft_l1``, ``cauchy``) on the error norm of each detection, minimised by iteratively
reweighted least squares. The noise level is estimated from the median error norm, which
ignores outliers.
"""

from __future__ import annotations

import numpy as np

from freipose.calibration.intrinsics import CalibrationError

__all__ = [
    "LOSSES",
    "MAX_VIEW_SCALE",
    "RAYLEIGH_MEDIAN",
    "camera_noise_sigmas",
    "irls_weights",
    "noise_sigma",
    "robust_cost",
    "robust_weights",
    "view_noise_scales",
]

LOSSES = ("linear", "huber", "soft_l1", "cauchy")
# median of the norm of isotropic 2D Gaussian noise of σ per axis (Rayleigh): σ √(2 ln 2)
RAYLEIGH_MEDIAN = float(np.sqrt(2 * np.log(2)))
# views are only down-weighted: up-weighting the quiet ones would shrink the covariance that
# the model-selection tests use
MAX_VIEW_SCALE = 1.0
# a camera with fewer inlier detections than this takes the global noise level
MIN_CAMERA_DETECTIONS = 30


def noise_sigma(errors: np.ndarray) -> float:
    """Per-axis detection noise σ (px) from reprojection error norms, robustly.

    For isotropic 2D Gaussian noise the error norm is Rayleigh distributed with median
    ``σ √(2 ln 2) ≈ 1.1774 σ``; the median ignores the outliers.

    Args:
        errors: (N,) error norms (px); NaN entries are ignored.

    Returns:
        σ in px, NaN without finite errors.
    """
    e = np.asarray(errors, np.float64)
    e = e[np.isfinite(e)]
    if e.size == 0:
        return float("nan")
    return float(np.median(e) / RAYLEIGH_MEDIAN)


def camera_noise_sigmas(
    errors: np.ndarray, cameras: np.ndarray, n_cameras: int, sigma: float, use: np.ndarray
) -> np.ndarray:
    """Per-camera detection noise σ_c (px) from each camera's own error norms, robustly.

    Cameras differ in how precisely their corners are found (lens, focus, motion blur, a
    board seen through its back), so each camera's noise is estimated from its own median
    error (:func:`noise_sigma`). A camera with fewer than :data:`MIN_CAMERA_DETECTIONS` used
    detections takes the global ``sigma``.

    Args:
        errors: (N,) error norms (px).
        cameras: (N,) camera index of each.
        n_cameras: number of cameras C.
        sigma: global per-axis noise σ (px), the fallback.
        use: (N,) bool, the detections that estimate the noise (the inliers).

    Returns:
        (C,) σ per camera (px).
    """
    e = np.asarray(errors, np.float64)
    cams = np.asarray(cameras)
    use = np.asarray(use, bool)
    out = np.full(n_cameras, float(sigma))
    for c in range(n_cameras):
        mine = use & (cams == c)
        if np.count_nonzero(mine) >= MIN_CAMERA_DETECTIONS:
            out[c] = noise_sigma(e[mine])
    return out


def view_noise_scales(
    errors: np.ndarray,
    groups: np.ndarray,
    sigma: float,
    prior_count: float = 8.0,
    use: np.ndarray | None = None,
) -> np.ndarray:
    """Per-observation residual scales ``σ / σ_view`` from the error norms of one view each.

    ``σ_view`` is the robust noise level of the observation's group (one board view: camera and
    frame) from its median error (:func:`noise_sigma`), shrunk towards the global ``σ`` as if
    the global level had been seen ``prior_count`` more times; the scales are clipped to
    [0.25, 1]: noisy views count less, none counts more than with equal weights (so the
    covariance behind the model-selection tests is not made over-confident), none vanishes.

    Args:
        errors: (N,) error norms (px).
        groups: (N,) int group (view) id of each.
        sigma: global per-axis noise σ (px).
        prior_count: weight of the global noise level, in observations.
        use: (N,) bool, the observations that estimate the views' noise (the inliers; default
            all); the others get their view's scale, or 1 in a view without any.

    Returns:
        (N,) residual scales.
    """
    e = np.asarray(errors, np.float64)
    g = np.asarray(groups)
    use = np.ones(len(e), bool) if use is None else np.asarray(use, bool)
    uniq, inv = np.unique(g, return_inverse=True)
    inv = inv.reshape(-1)
    counts = np.bincount(inv[use], minlength=len(uniq))
    # per-group medians, vectorized: sort the used errors by (group, error)
    iu, eu = inv[use], e[use]
    order = np.lexsort((eu, iu))
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    has = counts > 0
    lo = starts + np.maximum(counts - 1, 0) // 2
    hi = starts + counts // 2
    es = eu[order]
    med = np.zeros(len(uniq))
    med[has] = 0.5 * (es[lo[has]] + es[np.minimum(hi[has], len(es) - 1)])
    sv2 = (med / RAYLEIGH_MEDIAN) ** 2
    sv2 = (counts * sv2 + prior_count * sigma**2) / np.maximum(counts + prior_count, 1e-12)
    scale = np.clip(sigma / np.sqrt(np.maximum(sv2, 1e-24)), 0.25, MAX_VIEW_SCALE)
    scale[~has] = 1.0
    return scale[inv]


def robust_weights(e: np.ndarray, loss: str, k: float) -> np.ndarray:
    """IRLS weights of error norms.

    Args:
        e: (N,) error norms (px).
        loss: one of :data:`LOSSES`.
        k: the loss scale (px).

    Returns:
        (N,) weights.

    Raises:
        CalibrationError: an unknown loss.
    """
    if loss == "linear":
        return np.ones_like(e)
    if loss == "huber":
        return np.where(e <= k, 1.0, k / np.maximum(e, 1e-12))
    if loss == "cauchy":
        return 1.0 / (1.0 + (e / k) ** 2)
    if loss == "soft_l1":
        return 1.0 / np.sqrt(1.0 + (e / k) ** 2)
    raise CalibrationError(f"unknown loss {loss!r}; expected linear, huber, soft_l1 or cauchy")


def irls_weights(e: np.ndarray, loss: str, k: float, scale: np.ndarray | None) -> np.ndarray:
    """IRLS weights of error norms whose residuals are scaled.

    Args:
        e: (N,) error norms (px) before scaling.
        loss: one of :data:`LOSSES`.
        k: the loss scale (px).
        scale: (N,) factors the residuals are multiplied by, or None.

    Returns:
        (N,) weights of the unscaled residuals.
    """
    if scale is None:
        return robust_weights(e, loss, k)
    return scale**2 * robust_weights(e * scale, loss, k)


def robust_cost(e: np.ndarray, loss: str, k: float) -> float:
    """Total robust cost of error norms (``soft_l1`` for any loss not listed otherwise).

    Args:
        e: (N,) error norms (px).
        loss: one of :data:`LOSSES`.
        k: the loss scale (px).

    Returns:
        The cost (px²).
    """
    if loss == "linear":
        return float(np.sum(e**2))
    if loss == "huber":
        return float(np.sum(np.where(e <= k, e**2, 2 * k * e - k * k)))
    if loss == "cauchy":
        return float(np.sum(k * k * np.log1p((e / k) ** 2)))
    return float(np.sum(2 * k * k * (np.sqrt(1 + (e / k) ** 2) - 1)))
