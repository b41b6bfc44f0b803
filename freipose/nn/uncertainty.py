"""Per-keypoint uncertainty of the voxel network from its own disagreements, calibrated.

Two signals say how far a predicted keypoint may be from the truth, without a label:

* the disagreement of the views: the confidence-weighted RMS distance (mm, at the point's
  depth) of the refined pose P1 from the rays of the views' refined 2D points, over the
  views with a 2D point;
* the disagreement of the two estimates: the distance between P0 and P1 (mm).

Their root sum of squares, with a floor of half a voxel (the grid's own resolution),
is the raw uncertainty ``u``. A scale factor fitted on validation labels
(:func:`fit_scale`) turns it into ``sigma = scale * u`` (mm) such that 95 % of the
validation keypoints lie within ``2 sigma`` of the truth: ``sigma`` is written with the
poses (``extra/uncertainty``) and used by ``freipose labels select``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from freipose.geometry.camera import CameraRig
from freipose.geometry.projection import undistort_pixels

COVERAGE = 0.95
"""Share of the validation keypoints within two sigma that :func:`fit_scale` aims at."""


def view_disagreement(
    points3d: np.ndarray, points2d: np.ndarray, confidence2d: np.ndarray, rig: CameraRig
) -> np.ndarray:
    """Confidence-weighted RMS distance (mm) of 3D points from their views' rays.

    Args:
        points3d: (..., K, 3) world mm.
        points2d: (..., V, K, 2) full-image pixels of the V cameras of ``rig`` (NaN: none).
        confidence2d: (..., V, K) in [0, 1].
        rig: the V cameras.

    Returns:
        (..., K) mm; NaN where no view has a point or the 3D point is unknown.
    """
    V = confidence2d.shape[-2]
    d2 = np.zeros(confidence2d.shape)
    w = np.zeros(confidence2d.shape)
    for v, cam in enumerate(list(rig)[:V]):
        uv = points2d[..., v, :, :]
        xy = undistort_pixels(np.nan_to_num(uv), cam)  # (..., K, 2) normalized
        Xc = points3d @ np.asarray(cam.R).T + np.asarray(cam.t)
        lateral = xy * Xc[..., 2:3] - Xc[..., :2]
        ok = np.isfinite(uv).all(-1) & np.isfinite(lateral).all(-1)
        d2[..., v, :] = np.where(ok, (lateral**2).sum(-1), 0.0)
        w[..., v, :] = np.where(ok, np.clip(confidence2d[..., v, :], 0.0, 1.0), 0.0)
    total = w.sum(-2)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt((w * d2).sum(-2) / total)
    return np.where((total > 0) & np.isfinite(points3d).all(-1), rms, np.nan)


def raw_uncertainty(
    P0: np.ndarray,
    P1: np.ndarray,
    points2d: np.ndarray,
    confidence2d: np.ndarray,
    rigs: Sequence[CameraRig],
    voxel_size: float,
) -> np.ndarray:
    """The uncalibrated uncertainty ``u`` (mm) of a batch (see the module docstring).

    Samples that share a rig (the same object, as in a prediction run) are computed together.

    Args:
        P0: (B, K, 3) the 3D network's estimate (mm).
        P1: (B, K, 3) the refined estimate (mm).
        points2d: (B, V, K, 2) full-image pixels (NaN on padding views).
        confidence2d: (B, V, K) per-view confidences.
        rigs: the B rigs (each with at least the sample's real views).
        voxel_size: the network's voxel spacing (mm).

    Returns:
        (B, K) mm; NaN where P1 is unknown.
    """
    views = np.full(P1.shape[:2], np.nan)
    groups: dict[int, list[int]] = {}
    for b, rig in enumerate(rigs):
        groups.setdefault(id(rig), []).append(b)
    for idx in groups.values():
        rig, n = rigs[idx[0]], len(rigs[idx[0]])
        views[idx] = view_disagreement(P1[idx], points2d[idx, :n], confidence2d[idx, :n], rig)
    views = np.where(np.isfinite(views), views, 0.0)
    p01 = np.linalg.norm(P0 - P1, axis=-1)
    return np.sqrt(views**2 + p01**2 + (0.5 * voxel_size) ** 2)


@dataclass(frozen=True)
class Calibration:
    """The fitted scale of the raw uncertainty.

    Attributes:
        scale: ``sigma = scale * u``.
        coverage: share of the fitting keypoints within ``2 sigma`` (about :data:`COVERAGE`).
        keypoints: keypoints (instants x keypoints with a label) it was fitted on.
    """

    scale: float
    coverage: float
    keypoints: int


def fit_scale(errors: np.ndarray, raw: np.ndarray, coverage: float = COVERAGE) -> Calibration:
    """The scale that puts ``coverage`` of the keypoints within two sigma.

    Args:
        errors: (...) 3D errors (mm) against labels, NaN where unlabeled.
        raw: (...) raw uncertainties of the same keypoints (mm).
        coverage: the share aimed at.

    Returns:
        The :class:`Calibration` (scale NaN without a labeled keypoint).
    """
    e, u = np.asarray(errors, float).ravel(), np.asarray(raw, float).ravel()
    ok = np.isfinite(e) & np.isfinite(u) & (u > 0)
    if not ok.any():
        return Calibration(float("nan"), float("nan"), 0)
    scale = float(np.quantile(e[ok] / u[ok], coverage)) / 2.0
    covered = float(np.mean(e[ok] <= 2.0 * scale * u[ok]))
    return Calibration(scale, covered, int(ok.sum()))


def two_sigma_coverage(errors: np.ndarray, sigma: np.ndarray) -> float:
    """Share of the labeled keypoints whose error is at most ``2 sigma`` (NaN: none)."""
    e, s = np.asarray(errors, float).ravel(), np.asarray(sigma, float).ravel()
    ok = np.isfinite(e) & np.isfinite(s)
    return float(np.mean(e[ok] <= 2.0 * s[ok])) if ok.any() else float("nan")
