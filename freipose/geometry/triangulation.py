"""Triangulation from any subset of views: DLT, confidence-weighted, robust (RANSAC).

Observations have shape (..., C, 2) in *observed* (distorted) pixels with NaN where a view
did not see the point; the result is (..., 3) world mm, NaN where fewer than two views
(or inliers) remain.
"""

from __future__ import annotations

import itertools

import numpy as np

from freipose.geometry.camera import CameraRig
from freipose.geometry.distortion import undistort_normalized
from freipose.geometry.pinhole import remove_intrinsics
from freipose.geometry.projection import project_rig


def _check_obs(points2d: np.ndarray, rig: CameraRig) -> np.ndarray:
    uv = np.asarray(points2d, dtype=np.float64)
    if uv.ndim < 2 or uv.shape[-1] != 2 or uv.shape[-2] != len(rig):
        raise ValueError(
            f"2D observations must have shape (..., C={len(rig)}, 2) for a rig of "
            f"{len(rig)} cameras, got shape {uv.shape}"
        )
    return uv


def _normalized_obs(uv: np.ndarray, rig: CameraRig) -> np.ndarray:
    """Undistorted normalized coordinates (..., C, 2), all cameras at once."""
    return undistort_normalized(remove_intrinsics(uv, rig.K), rig.dist)


def _dlt(xy: np.ndarray, Rt: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted homogeneous DLT.

    xy: (N, C, 2) normalized coords, Rt: (C, 3, 4), w: (N, C) weights (0 = skip).
    Returns (N, 3); NaN where fewer than two views have positive weight.
    """
    n, c = xy.shape[:2]
    ok = np.isfinite(xy).all(-1) & np.isfinite(w) & (w > 0)
    ww = np.where(ok, w, 0.0)
    xs = np.where(ok, xy[..., 0], 0.0)
    ys = np.where(ok, xy[..., 1], 0.0)
    r1 = xs[..., None] * Rt[None, :, 2] - Rt[None, :, 0]  # (N, C, 4)
    r2 = ys[..., None] * Rt[None, :, 2] - Rt[None, :, 1]
    A = np.concatenate([r1 * ww[..., None], r2 * ww[..., None]], axis=1)  # (N, 2C, 4)
    # Rows from unit-norm weighted equations keep the SVD well conditioned.
    out = np.full((n, 3), np.nan)
    valid = ok.sum(-1) >= 2
    if np.any(valid):
        _, _, vt = np.linalg.svd(A[valid])
        Xh = vt[:, -1]
        with np.errstate(divide="ignore", invalid="ignore"):
            X = Xh[:, :3] / Xh[:, 3:4]
        out[valid] = X
    return out


def _rt(rig: CameraRig) -> np.ndarray:
    return np.concatenate([rig.R, rig.t[:, :, None]], axis=2)  # (C, 3, 4)


def triangulate(points2d: np.ndarray, rig: CameraRig) -> np.ndarray:
    """Linear (DLT) triangulation from all views that observed each point.

    Args:
        points2d: (..., C, 2) observed pixels, NaN where missing.
        rig: the cameras (C of them).

    Returns:
        (..., 3) world points in mm; NaN where fewer than two views observed the point.
    """
    return triangulate_weighted(points2d, np.ones(np.shape(points2d)[:-1]), rig)


def triangulate_weighted(
    points2d: np.ndarray, weights: np.ndarray, rig: CameraRig, refine: bool = False
) -> np.ndarray:
    """Confidence-weighted DLT triangulation.

    Args:
        points2d: (..., C, 2) observed pixels, NaN where missing.
        weights: (..., C) non-negative confidences; 0 or NaN skips the view.
        rig: the cameras.
        refine: polish the result by weighted nonlinear least squares on pixel errors.

    Returns:
        (..., 3) world points in mm; NaN where fewer than two views have weight > 0.
    """
    uv = _check_obs(points2d, rig)
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != uv.shape[:-1]:
        raise ValueError(f"weights must have shape {uv.shape[:-1]}, got shape {w.shape}")
    if np.any(w < 0):
        raise ValueError("triangulation weights must be non-negative")
    lead = uv.shape[:-2]
    c = len(rig)
    flat_uv = uv.reshape(-1, c, 2)
    flat_w = w.reshape(-1, c)
    X = _dlt(_normalized_obs(flat_uv, rig), _rt(rig), flat_w)
    if refine:
        X = _refine(X, flat_uv, np.where(np.isfinite(flat_w), flat_w, 0.0), rig)
    return X.reshape(lead + (3,))


def reprojection_errors(points3d: np.ndarray, points2d: np.ndarray, rig: CameraRig) -> np.ndarray:
    """Pixel distance between observations and the projections of 3D points.

    Args:
        points3d: (..., 3) world points.
        points2d: (..., C, 2) observations.
        rig: the cameras.

    Returns:
        (..., C) errors in pixels; NaN where the observation or the point is missing.
    """
    uv = _check_obs(points2d, rig)
    X = np.asarray(points3d, dtype=np.float64)
    if X.shape != uv.shape[:-2] + (3,):
        raise ValueError(
            f"points3d must have shape {uv.shape[:-2] + (3,)} to match points2d {uv.shape}, "
            f"got {X.shape}"
        )
    proj = project_rig(X[..., None, :], rig)[..., 0, :]  # (..., C, 2)
    return np.linalg.norm(proj - uv, axis=-1)


def _refine(
    X: np.ndarray, uv: np.ndarray, w: np.ndarray, rig: CameraRig, iterations: int = 10
) -> np.ndarray:
    """Weighted Gauss-Newton on pixel reprojection errors. X (N,3), uv (N,C,2), w (N,C)."""
    X = X.copy()
    obs = np.isfinite(uv).all(-1) & (w > 0)
    sw = np.sqrt(np.where(obs, w, 0.0))[..., None]  # (N, C, 1)
    uv0 = np.where(obs[..., None], uv, 0.0)
    active = np.isfinite(X).all(-1) & (obs.sum(-1) >= 2)
    if not np.any(active):
        return X
    h = 1e-4  # mm, central differences

    def residual(P: np.ndarray) -> np.ndarray:
        pr = project_rig(P[:, None, :], rig)[:, :, 0, :]  # (n, C, 2)
        r = np.where(obs_a[..., None], pr - uv_a, 0.0) * sw_a
        return np.nan_to_num(r, nan=0.0).reshape(len(P), -1)

    Xa = X[active]
    obs_a, uv_a, sw_a = obs[active], uv0[active], sw[active]
    r = residual(Xa)
    cost = (r**2).sum(-1)
    lam = np.full(len(Xa), 1e-3)
    for _ in range(iterations):
        J = np.stack(
            [(residual(Xa + h * e) - residual(Xa - h * e)) / (2 * h) for e in np.eye(3)], axis=-1
        )  # (n, 2C, 3)
        JtJ = J.transpose(0, 2, 1) @ J
        g = J.transpose(0, 2, 1) @ r[..., None]
        A = JtJ + lam[:, None, None] * np.eye(3) * (
            np.trace(JtJ, axis1=1, axis2=2)[:, None, None] / 3 + 1e-12
        )
        try:
            step = np.linalg.solve(A, g)[..., 0]
        except np.linalg.LinAlgError:
            break
        Xn = Xa - step
        rn = residual(Xn)
        cn = (rn**2).sum(-1)
        better = np.isfinite(cn) & (cn < cost)
        Xa = np.where(better[:, None], Xn, Xa)
        r = np.where(better[:, None], rn, r)
        cost = np.where(better, cn, cost)
        lam = np.where(better, lam * 0.3, lam * 10)
    X[active] = Xa
    return X


def triangulate_robust(
    points2d: np.ndarray,
    rig: CameraRig,
    threshold: float = 10.0,
    weights: np.ndarray | None = None,
    min_inliers: int = 2,
    refine: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Robust triangulation: exhaustive RANSAC over view pairs, then refinement on inliers.

    Every pair of observing views proposes a point; the proposal with the most views whose
    reprojection error is below ``threshold`` pixels wins (ties: smallest summed inlier
    error). The point is re-triangulated from its inliers (weighted DLT, then nonlinear
    least squares on pixel errors when ``refine``).

    Args:
        points2d: (..., C, 2) observed pixels, NaN where missing.
        rig: the cameras.
        threshold: inlier threshold in pixels.
        weights: optional (..., C) confidences used in the final fit.
        min_inliers: fewest inlier views for a valid point (>= 2).
        refine: nonlinear refinement on the inliers.

    Returns:
        ``(points3d, inliers)``: (..., 3) world mm (NaN where no consensus) and
        (..., C) boolean inlier masks.
    """
    uv = _check_obs(points2d, rig)
    if min_inliers < 2:
        raise ValueError(f"min_inliers must be at least 2, got {min_inliers}")
    c = len(rig)
    lead = uv.shape[:-2]
    flat = uv.reshape(-1, c, 2)
    n = flat.shape[0]
    if weights is None:
        w = np.ones((n, c))
    else:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != uv.shape[:-1]:
            raise ValueError(f"weights must have shape {uv.shape[:-1]}, got shape {w.shape}")
        w = w.reshape(n, c)
    w = np.where(np.isfinite(w) & (w > 0), w, 0.0)
    obs = np.isfinite(flat).all(-1) & (w > 0)
    xy = _normalized_obs(flat, rig)
    Rt = _rt(rig)
    pairs = list(itertools.combinations(range(c), 2))
    best_count = np.zeros(n, dtype=np.int64)
    best_err = np.full(n, np.inf)
    best_in = np.zeros((n, c), dtype=bool)
    for i, j in pairs:
        sel = obs[:, i] & obs[:, j]
        if not np.any(sel):
            continue
        pw = np.zeros((int(sel.sum()), c))
        pw[:, [i, j]] = 1.0
        Xp = _dlt(xy[sel], Rt, pw)
        err = reprojection_errors(Xp, flat[sel], rig)  # (m, C)
        inl = (err < threshold) & obs[sel]
        cnt = inl.sum(-1)
        serr = np.where(inl, err, 0.0).sum(-1)
        cur_c, cur_e = best_count[sel], best_err[sel]
        better = (cnt > cur_c) | ((cnt == cur_c) & (serr < cur_e))
        idx = np.flatnonzero(sel)[better]
        best_count[idx] = cnt[better]
        best_err[idx] = serr[better]
        best_in[idx] = inl[better]
    ok = best_count >= min_inliers
    X = np.full((n, 3), np.nan)
    if np.any(ok):
        wi = np.where(best_in[ok], w[ok], 0.0)
        Xo = _dlt(xy[ok], Rt, wi)
        if refine:
            Xo = _refine(Xo, flat[ok], wi, rig)
        X[ok] = Xo
    best_in[~ok] = False
    return X.reshape(lead + (3,)), best_in.reshape(lead + (c,))
