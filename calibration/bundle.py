"""Multi-camera bundle adjustment of intrinsics, distortion, extrinsics and board poses.

Levenberg-Marquardt with analytic Jacobians and the Schur complement over the per-frame board
poses (each residual depends on one camera and one board pose, so the normal equations reduce to
a small dense system in the camera parameters), a robust loss (iteratively reweighted), and
outlier rejection between rounds, in which every board view's residuals are also weighted by
its own noise level (views with motion blur or a steep board are noisier than the rest).
``method="scipy"`` uses ``scipy.optimize.least_squares``
with a sparse Jacobian pattern instead (slower; kept as a cross-check).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

logger = logging.getLogger(__name__)

__all__ = [
    "BundleResult",
    "Observations",
    "bundle_adjust",
    "board_point_offsets",
    "camera_covariance",
    "noise_sigma",
    "project_observations",
    "rodrigues",
]

N_CAM = 15  # fx fy cx cy k1 k2 p1 p2 k3 r1 r2 r3 t1 t2 t3
# views are only down-weighted: up-weighting the quiet ones shrinks the covariance that the
# model-selection tests use (on a rendered rig it freed a principal point the truth does not have)
MAX_VIEW_SCALE = 1.0


def rodrigues(r: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) -> rotation matrices (..., 3, 3) (vectorized Rodrigues)."""
    r = np.asarray(r, dtype=np.float64)
    theta = np.linalg.norm(r, axis=-1)[..., None, None]
    small = theta < 1e-12
    safe = np.where(small, 1.0, theta)
    k = r / safe[..., 0]
    K = np.zeros(r.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -k[..., 2], k[..., 1]
    K[..., 1, 0], K[..., 1, 2] = k[..., 2], -k[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -k[..., 1], k[..., 0]
    s, c = np.sin(theta), np.cos(theta)
    eye = np.broadcast_to(np.eye(3), K.shape)
    R = eye + s * K + (1 - c) * (K @ K)
    # first-order for tiny angles
    Kr = np.zeros_like(K)
    Kr[..., 0, 1], Kr[..., 0, 2] = -r[..., 2], r[..., 1]
    Kr[..., 1, 0], Kr[..., 1, 2] = r[..., 2], -r[..., 0]
    Kr[..., 2, 0], Kr[..., 2, 1] = -r[..., 1], r[..., 0]
    return np.where(small, eye + Kr, R)


MIN_F_SCALE = 0.05  # px: floor of the estimated robust-loss scale
# median of the norm of isotropic 2D Gaussian noise of σ per axis (Rayleigh): σ √(2 ln 2)
RAYLEIGH_MEDIAN = float(np.sqrt(2 * np.log(2)))
# Levenberg-Marquardt stops when a step lowers the cost by less than this fraction: the cost
# is ~σ² per residual, and moving a parameter by one standard error changes it by ~σ², i.e.
# ~1 / (2 N) of it (1e-4 for 5000 detections), 100 times more than this tolerance
REL_TOL = 1e-6
# outlier-rejection rounds stop when at most this fraction of the detections change status
# (and the loss scale changes by at most 20 %)
ROUND_TOL = 1e-3


def _one_blas_thread():
    """Context limiting BLAS to one thread: the solver's matrices are small (cameras x 15
    squared, batches of 15 x 24 blocks), where BLAS threads cost more than they save; on a busy
    machine their spinning made the adjustment 5x slower. (``threadpoolctl`` comes with
    scikit-learn.)"""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - scikit-learn depends on it
        from contextlib import nullcontext

        return nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


def noise_sigma(errors: np.ndarray) -> float:
    """Per-axis detection noise σ (px) from reprojection error norms (N,), robustly.

    For isotropic 2D Gaussian noise the error norm is Rayleigh distributed with median
    ``σ √(2 ln 2) ≈ 1.1774 σ``; the median ignores the outliers.
    """
    e = np.asarray(errors, np.float64)
    e = e[np.isfinite(e)]
    if e.size == 0:
        return float("nan")
    return float(np.median(e) / RAYLEIGH_MEDIAN)


def matrix_to_rvec(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (3,) rotation vector."""
    import cv2

    rv, _ = cv2.Rodrigues(np.asarray(R, np.float64))
    return rv.reshape(3)


@dataclass(frozen=True)
class Observations:
    """Flat list of detections: camera index (N,), frame index (N,), board point (N,3) mm,
    pixel (N,2)."""

    cam: np.ndarray
    frame: np.ndarray
    point: np.ndarray
    uv: np.ndarray

    def __len__(self) -> int:
        return int(self.cam.shape[0])

    def subset(self, keep: np.ndarray) -> Observations:
        return Observations(self.cam[keep], self.frame[keep], self.point[keep], self.uv[keep])


def project_observations(cam_params: np.ndarray, frame_params: np.ndarray, obs: Observations):
    """Project every observation's board point.

    Args:
        cam_params: (C, 15) fx fy cx cy k1 k2 p1 p2 k3 rvec t (world→camera).
        frame_params: (F, 6) rvec t (board→world).

    Returns:
        (N, 2) pixels and (N,) depth in the camera.
    """
    Rf = rodrigues(frame_params[:, :3])
    Rc = rodrigues(cam_params[:, 9:12])
    fi, ci = obs.frame, obs.cam
    Xw = np.einsum("nij,nj->ni", Rf[fi], obs.point) + frame_params[fi, 3:]
    Xc = np.einsum("nij,nj->ni", Rc[ci], Xw) + cam_params[ci, 12:]
    z = Xc[:, 2]
    zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
    x, y = Xc[:, 0] / zs, Xc[:, 1] / zs
    p = cam_params[ci]
    k1, k2, p1, p2, k3 = p[:, 4], p[:, 5], p[:, 6], p[:, 7], p[:, 8]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    u = p[:, 0] * xd + p[:, 2]
    v = p[:, 1] * yd + p[:, 3]
    return np.stack([u, v], axis=1), z


@dataclass(frozen=True)
class BundleResult:
    """Refined parameters and diagnostics.

    Attributes:
        cam_params: (C, 15) fx fy cx cy k1 k2 p1 p2 k3 rvec t.
        frame_params: (F, 6) board→world rvec t for the frames in ``frames``.
        frames: (F,) video frame index of each board pose.
        obs: the observations (all, before rejection).
        inliers: (N,) bool, kept after outlier rejection.
        errors: (N,) final reprojection error (px) of every observation.
        rounds, nfev, seconds: solver statistics.
        loss, f_scale: the robust loss and the scale (px) of the last round.
        view_scale: (N,) the factor every observation's residual was scaled by in the last
            round (``σ / σ_view``, the global over its board view's noise level; ones without
            view weighting).
    """

    cam_params: np.ndarray
    frame_params: np.ndarray
    frames: np.ndarray
    obs: Observations
    inliers: np.ndarray
    errors: np.ndarray
    initial_rms: float
    rounds: int
    nfev: int
    seconds: float
    loss: str = "huber"
    f_scale: float = 1.0
    view_scale: np.ndarray | None = None


def _irls_weights(e: np.ndarray, loss: str, k: float, scale: np.ndarray | None) -> np.ndarray:
    """IRLS weights of error norms ``e`` (N,) whose residuals are scaled by ``scale`` (N,)."""
    if scale is None:
        return _robust_weights(e, loss, k)
    return scale**2 * _robust_weights(e * scale, loss, k)


def view_noise_scales(
    errors: np.ndarray,
    groups: np.ndarray,
    sigma: float,
    prior_count: float = 8.0,
    use: np.ndarray | None = None,
) -> np.ndarray:
    """Per-observation residual scales ``σ / σ_view`` (N,) from the error norms of one view each.

    ``σ_view`` is the robust noise level of the observation's group (one board view: camera and
    frame) from its median error (:func:`noise_sigma`), shrunk towards the global ``σ`` as if
    the global level had been seen ``prior_count`` more times; the scales are clipped to
    [0.25, 1]: noisy views count less, none counts more than with equal weights (so the
    covariance behind the model-selection tests is not made over-confident), none vanishes.

    Args:
        errors: (N,) error norms (px).
        groups: (N,) int group (view) id of each.
        sigma: global per-axis noise σ (px).
        use: (N,) bool, the observations that estimate the views' noise (the inliers; default
            all); the others get their view's scale, or 1 in a view without any.
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


def _run_starts(keys: np.ndarray) -> np.ndarray:
    """Indices (R,) where the runs of equal values of a sorted key array (K,) start."""
    if len(keys) == 0:
        return np.zeros(0, np.int64)
    return np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])


class _Segments:
    """Sums of consecutive rows that share a sorted key (K,) in [0, n): ``self(x)`` (K, ...)
    -> (n, ...), zero for keys that do not occur."""

    def __init__(self, keys: np.ndarray, n: int):
        self.n = n
        self.starts = _run_starts(keys)
        self.keys = keys[self.starts]

    def __call__(self, x: np.ndarray) -> np.ndarray:
        out = np.zeros((self.n,) + x.shape[1:])
        if len(self.starts):
            out[self.keys] = np.add.reduceat(x, self.starts, axis=0)
        return out


class _Problem:
    """Residuals and analytic Jacobians with local (left-multiplied) rotation updates.

    State: intrinsics (C, 9), camera rotations (C, 3, 3), translations (C, 3), board rotations
    (F, 3, 3), translations (F, 3). A camera's 15 local parameters are fx fy cx cy k1 k2 p1 p2
    k3, δrot (3), δt (3); a board's 6 are δrot (3), δt (3).
    """

    def __init__(self, obs: Observations, C: int, F: int):
        order = np.lexsort((obs.frame, obs.cam))
        self.obs = obs.subset(order)
        self.order = order
        key = self.obs.cam * F + self.obs.frame
        starts = _run_starts(key)
        self.n_pairs = len(starts)
        # each observation's (camera, frame) pair and its slot in that pair: the normal
        # equations are sums over pairs, done as batched products of padded (pair, slot) blocks
        counts = np.diff(np.r_[starts, len(key)])
        pair_id = np.repeat(np.arange(self.n_pairs), counts)
        slot = np.arange(len(key)) - starts[pair_id]
        self.slots = int(counts.max(initial=0))
        self.flat_slot = pair_id * self.slots + slot  # into (pairs * slots)
        self.pair_cam = self.obs.cam[starts]
        self.pair_frame = self.obs.frame[starts]
        # sums over a camera's / a board pose's pairs as segment sums (np.add.reduceat): the
        # pairs are sorted by camera; by_frame sorts them by board pose
        self.cam_sum = _Segments(self.pair_cam, C)
        self.by_frame = np.argsort(self.pair_frame, kind="stable")
        self.frame_sum = _Segments(self.pair_frame[self.by_frame], F)
        self.C, self.F = C, F

    def residuals(self, intr, Rc, tc, Rf, tf):
        o = self.obs
        Xw = np.einsum("nij,nj->ni", Rf[o.frame], o.point) + tf[o.frame]
        Xc = np.einsum("nij,nj->ni", Rc[o.cam], Xw) + tc[o.cam]
        z = Xc[:, 2]
        zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
        x, y = Xc[:, 0] / zs, Xc[:, 1] / zs
        p = intr[o.cam]
        k1, k2, p1, p2, k3 = p[:, 4], p[:, 5], p[:, 6], p[:, 7], p[:, 8]
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        r = np.stack([p[:, 0] * xd + p[:, 2], p[:, 1] * yd + p[:, 3]], axis=1) - o.uv
        return r, (Xw, Xc, zs, x, y, r2, radial, xd, yd, p)

    def jacobians(self, Rc, Rf, cache):
        o = self.obs
        Xw, Xc, z, x, y, r2, radial, xd, yd, p = cache
        N = len(o)
        fx, fy = p[:, 0], p[:, 1]
        k1, k2, p1, p2, k3 = p[:, 4], p[:, 5], p[:, 6], p[:, 7], p[:, 8]
        Jc = np.zeros((N, 2, 15))
        Jc[:, 0, 0] = xd
        Jc[:, 1, 1] = yd
        Jc[:, 0, 2] = 1.0
        Jc[:, 1, 3] = 1.0
        r4 = r2 * r2
        Jc[:, 0, 4:9] = fx[:, None] * np.stack(
            [x * r2, x * r4, 2 * x * y, r2 + 2 * x * x, x * r4 * r2], 1
        )
        Jc[:, 1, 4:9] = fy[:, None] * np.stack(
            [y * r2, y * r4, r2 + 2 * y * y, 2 * x * y, y * r4 * r2], 1
        )
        # d(xd, yd)/d(x, y)
        dr = k1 + 2 * k2 * r2 + 3 * k3 * r4  # d radial / d r2
        dxd_dx = radial + 2 * x * x * dr + 2 * p1 * y + 6 * p2 * x
        dxd_dy = 2 * x * y * dr + 2 * p1 * x + 2 * p2 * y
        dyd_dx = 2 * x * y * dr + 2 * p1 * x + 2 * p2 * y
        dyd_dy = radial + 2 * y * y * dr + 6 * p1 * y + 2 * p2 * x
        A = np.empty((N, 2, 2))
        A[:, 0, 0], A[:, 0, 1] = fx * dxd_dx, fx * dxd_dy
        A[:, 1, 0], A[:, 1, 1] = fy * dyd_dx, fy * dyd_dy
        Bn = np.zeros((N, 2, 3))  # d(x, y)/d Xc
        Bn[:, 0, 0] = 1 / z
        Bn[:, 1, 1] = 1 / z
        Bn[:, 0, 2] = -x / z
        Bn[:, 1, 2] = -y / z
        D = A @ Bn  # (N, 2, 3) d uv / d Xc
        # the rotation perturbation acts on Rc Xw: d uv / d δrot = -D [Rc Xw]x, whose rows are
        # (Rc Xw) x (rows of D)
        RcXw = np.einsum("nij,nj->ni", Rc[o.cam], Xw)
        Jc[:, :, 9:12] = np.cross(RcXw[:, None, :], D)
        Jc[:, :, 12:15] = D
        DR = D @ Rc[o.cam]  # d uv / d Xw
        RfX = np.einsum("nij,nj->ni", Rf[o.frame], o.point)
        Jf = np.empty((N, 2, 6))
        Jf[:, :, :3] = np.cross(RfX[:, None, :], DR)
        Jf[:, :, 3:] = DR
        return Jc, Jf


def _robust_weights(e: np.ndarray, loss: str, k: float) -> np.ndarray:
    """IRLS weights for the error norms ``e`` (N,)."""
    if loss == "linear":
        return np.ones_like(e)
    if loss == "huber":
        return np.where(e <= k, 1.0, k / np.maximum(e, 1e-12))
    if loss == "cauchy":
        return 1.0 / (1.0 + (e / k) ** 2)
    if loss == "soft_l1":
        return 1.0 / np.sqrt(1.0 + (e / k) ** 2)
    raise ValueError(f"unknown loss {loss!r}; expected linear, huber, soft_l1 or cauchy")


def _robust_cost(e: np.ndarray, loss: str, k: float) -> float:
    if loss == "linear":
        return float(np.sum(e**2))
    if loss == "huber":
        return float(np.sum(np.where(e <= k, e**2, 2 * k * e - k * k)))
    if loss == "cauchy":
        return float(np.sum(k * k * np.log1p((e / k) ** 2)))
    return float(np.sum(2 * k * k * (np.sqrt(1 + (e / k) ** 2) - 1)))


def _exp_so3(w: np.ndarray) -> np.ndarray:
    return rodrigues(w)


def _tie_focal(Jc: np.ndarray, cam: np.ndarray, tie: np.ndarray | None) -> np.ndarray:
    """Camera Jacobian (N, 2, 15) with fy = fx for the cameras in ``tie`` (C,): the fx column
    moves both focal lengths (the fy column is then fixed)."""
    if tie is not None and tie.any():
        Jc[:, :, 0] += tie[cam][:, None] * Jc[:, :, 1]
    return Jc


def _normal_equations(prob: _Problem, Rc, Rf, cache, r, w, free, tie=None):
    """Weighted Gauss-Newton blocks: Hcc (C,15,15), Hff (F,6,6), Hcf (C,F,15,6), gc (C,15),
    gf (F,6); fixed camera parameters get identity rows (and zero gradient)."""
    C, F = prob.C, prob.F
    pc, pf = prob.pair_cam, prob.pair_frame
    Jc, Jf = prob.jacobians(Rc, Rf, cache)
    Jc = _tie_focal(Jc, prob.obs.cam, tie)
    Jc = Jc * free.astype(float)[prob.obs.cam][:, None, :]
    sw = np.sqrt(w)  # robust weights are >= 0
    n_pairs, S = prob.n_pairs, prob.slots
    # sqrt(w) [J r], padded per (camera, frame) pair: (pairs, 2 slots, 15 + 6 + 1)
    M = np.zeros((n_pairs * S, 2, 22))
    M[prob.flat_slot] = np.concatenate([Jc, Jf, r[:, :, None]], axis=2) * sw[:, None, None]
    M = M.reshape(n_pairs, 2 * S, 22)
    G = M[:, :, :21].transpose(0, 2, 1) @ M  # (pairs, 21, 22): [Jc Jf]^T [Jc Jf r]
    Hcc = prob.cam_sum(G[:, :15, :15])
    gc = prob.cam_sum(G[:, :15, 21])
    Gf = G[prob.by_frame, 15:]
    Hff = prob.frame_sum(Gf[:, :, 15:21])
    gf = prob.frame_sum(Gf[:, :, 21])
    Hcf = np.zeros((C, F, 15, 6))
    Hcf[pc, pf] = G[:, :15, 15:21]
    fixed = ~free
    for c in range(C):
        idx = np.flatnonzero(fixed[c])
        Hcc[c, idx, :] = 0
        Hcc[c, :, idx] = 0
        Hcc[c, idx, idx] = 1.0
    gc[fixed] = 0.0
    return Hcc, Hff, Hcf, gc, gf


def _schur(Hcc, Hff, Hcf, gc, gf):
    """Reduced camera system ``S dcam = rhs`` and ``Hff⁻¹`` (F, 6, 6)."""
    C, F = Hcf.shape[:2]
    P = C * 15
    Hff_inv = np.linalg.inv(Hff)
    Hcf_flat = Hcf.transpose(0, 2, 1, 3).reshape(P, F * 6)
    Y = Hcf @ Hff_inv
    Y_flat = Y.transpose(0, 2, 1, 3).reshape(P, F * 6)
    S = np.zeros((P, P))
    for c in range(C):
        S[c * 15 : (c + 1) * 15, c * 15 : (c + 1) * 15] = Hcc[c]
    S -= Y_flat @ Hcf_flat.T
    rhs = -gc.reshape(P) + Y_flat @ gf.reshape(F * 6)
    return S, rhs, Hff_inv


def _solve(cam0, free, frame0, obs, loss, f_scale, max_iter, tie=None, scale=None):
    """Levenberg-Marquardt with the Schur complement over the board poses; ``scale`` (N,) or
    None multiplies each observation's residual (per-view noise weighting)."""
    C, F = cam0.shape[0], frame0.shape[0]
    prob = _Problem(obs, C, F)
    if scale is not None:
        scale = np.asarray(scale)[prob.order]  # the problem sorts the observations
    intr = cam0[:, :9].copy()
    if tie is not None:
        intr[tie, 1] = intr[tie, 0]
    Rc = rodrigues(cam0[:, 9:12])
    tc = cam0[:, 12:15].copy()
    Rf = rodrigues(frame0[:, :3])
    tf = frame0[:, 3:].copy()
    freef = free.astype(float)

    def cost_of(intr, Rc, tc, Rf, tf):
        r, cache = prob.residuals(intr, Rc, tc, Rf, tf)
        e = np.linalg.norm(r, axis=1)
        return _robust_cost(e if scale is None else e * scale, loss, f_scale), r, e, cache

    cost, r, e, cache = cost_of(intr, Rc, tc, Rf, tf)
    lam = 1e-3
    it = 0
    nfev = 1
    for it in range(1, max_iter + 1):  # noqa: B007
        w = _irls_weights(e, loss, f_scale, scale)
        Hcc, Hff, Hcf, gc, gf = _normal_equations(prob, Rc, Rf, cache, r, w, free, tie)
        improved = False
        for _ in range(12):
            # damped system
            Hcc_d = Hcc.copy()
            dc = np.einsum("cii->ci", Hcc_d)
            dc += lam * np.maximum(dc, 1e-9)
            Hff_d = Hff.copy()
            df = np.einsum("fii->fi", Hff_d)
            df += lam * np.maximum(df, 1e-9) + 1e-12
            S, rhs, Hff_inv = _schur(Hcc_d, Hff_d, Hcf, gc, gf)
            try:
                dcam = np.linalg.solve(S, rhs)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            dcam = dcam.reshape(C, 15) * freef
            dfr = -np.einsum("fij,fj->fi", Hff_inv, gf + np.einsum("cfij,ci->fj", Hcf, dcam))
            n_intr = intr + dcam[:, :9]
            if tie is not None:
                n_intr[tie, 1] = n_intr[tie, 0]
            n_Rc = _exp_so3(dcam[:, 9:12]) @ Rc
            n_tc = tc + dcam[:, 12:15] + 0.0
            # left rotation update of Rc acts on (Rc Xw); t is updated additively
            n_Rf = _exp_so3(dfr[:, :3]) @ Rf
            n_tf = tf + dfr[:, 3:]
            n_cost, n_r, n_e, n_cache = cost_of(n_intr, n_Rc, n_tc, n_Rf, n_tf)
            nfev += 1
            if np.isfinite(n_cost) and n_cost < cost:
                rel = (cost - n_cost) / max(cost, 1e-300)
                intr, Rc, tc, Rf, tf = n_intr, n_Rc, n_tc, n_Rf, n_tf
                cost, r, e, cache = n_cost, n_r, n_e, n_cache
                lam = max(lam / 3, 1e-9)
                improved = True
                break
            lam *= 4
        if not improved or rel < REL_TOL:
            break
    cam = np.zeros_like(cam0)
    cam[:, :9] = intr
    cam[:, 9:12] = np.stack([matrix_to_rvec(R) for R in Rc])
    cam[:, 12:15] = tc
    fr = np.zeros_like(frame0)
    fr[:, :3] = np.stack([matrix_to_rvec(R) for R in Rf]) if F else np.zeros((0, 3))
    fr[:, 3:] = tf
    return cam, fr, nfev


def _sparsity(obs: Observations, cam_cols: np.ndarray, n_cam_free: int, F: int):
    from scipy.sparse import coo_matrix

    N = len(obs)
    rows, cols = [], []
    r0 = 2 * np.arange(N)
    cc = cam_cols[obs.cam]  # (N, 15), -1 if fixed
    for k in range(N_CAM):
        ok = cc[:, k] >= 0
        for d in (0, 1):
            rows.append(r0[ok] + d)
            cols.append(cc[ok, k])
    for k in range(6):
        for d in (0, 1):
            rows.append(r0 + d)
            cols.append(n_cam_free + 6 * obs.frame + k)
    rows_a = np.concatenate(rows)
    cols_a = np.concatenate(cols)
    data = np.ones(len(rows_a), dtype=np.int8)
    return coo_matrix((data, (rows_a, cols_a)), shape=(2 * N, n_cam_free + 6 * F)).tocsr()


def _solve_scipy(cam0, free, frame0, obs, loss, f_scale, max_iter, tie=None, scale=None):
    """``scipy.optimize.least_squares`` (TRF, LSMR) with a finite-difference sparse Jacobian."""
    from scipy.optimize import least_squares

    C, F = cam0.shape[0], frame0.shape[0]
    cam_cols = np.full((C, N_CAM), -1, dtype=np.int64)
    cam_cols[free] = np.arange(int(free.sum()))
    n_cam_free = int(free.sum())

    def unpack(x):
        cam = cam0.copy()
        cam[free] = x[:n_cam_free]
        if tie is not None:
            cam[tie, 1] = cam[tie, 0]
        return cam, x[n_cam_free:].reshape(F, 6)

    def fun(x):
        cam, fr = unpack(x)
        uv, _z = project_observations(cam, fr, obs)
        r = uv - obs.uv
        return (r if scale is None else r * scale[:, None]).ravel()

    x0 = np.concatenate([cam0[free], frame0.ravel()])
    res = least_squares(
        fun,
        x0,
        jac_sparsity=_sparsity(obs, cam_cols, n_cam_free, F),
        loss=loss,
        f_scale=f_scale,
        x_scale="jac",
        method="trf",
        tr_solver="lsmr",
        ftol=1e-10,
        xtol=1e-10,
        gtol=1e-10,
        max_nfev=2 * max_iter,
    )
    cam, fr = unpack(res.x)
    return cam, fr, int(res.nfev)


def bundle_adjust(
    cam_params: np.ndarray,
    free: np.ndarray,
    frame_params: np.ndarray,
    frames: np.ndarray,
    obs: Observations,
    loss: str = "huber",
    f_scale: float | None = None,
    max_rounds: int = 4,
    outlier_px: float = 0.5,
    max_iter: int = 100,
    method: str = "lm",
    outlier_sigmas: float = 5.0,
    start_f_scale: float = 1.0,
    equal_focal: np.ndarray | None = None,
    keep: np.ndarray | None = None,
    view_weighting: bool = True,
    view_scale: np.ndarray | None = None,
) -> BundleResult:
    """Jointly refine cameras and board poses.

    Args:
        cam_params: (C, 15) initial fx fy cx cy k1 k2 p1 p2 k3 rvec t (world→camera).
        free: (C, 15) bool, which camera parameters are optimised (fix one camera's extrinsics
            to remove the gauge freedom).
        frame_params: (F, 6) initial board→world rvec t.
        frames: (F,) video frame indices (bookkeeping only).
        obs: observations whose ``frame`` indexes ``frame_params``.
        loss: robust loss (``huber``, ``soft_l1``, ``cauchy`` or ``linear``).
        f_scale: scale of the robust loss (px); ``None`` estimates it from the data: the first
            round uses ``start_f_scale`` (px), later rounds ``2 σ`` (at least 0.05 px), where
            ``σ`` is the detection noise per axis estimated from the inliers' median error (for
            2D Gaussian noise the error norm's median is ``1.1774 σ``).
        max_rounds: solve / reject rounds.
        method: ``"lm"`` (Levenberg-Marquardt with Schur complement, analytic Jacobian) or
            ``"scipy"`` (``least_squares`` with a sparse finite-difference Jacobian).
        outlier_px, outlier_sigmas: a detection is rejected when its error exceeds
            ``max(outlier_px, outlier_sigmas * σ)`` after a round.
        equal_focal: (C,) bool, cameras whose fy is tied to fx (square pixels; their
            ``free[:, 1]`` must be False); ``None`` = none.
        keep: (N,) bool, the detections to start from (e.g. the inliers of a previous
            adjustment of the same observations); ``None`` = all but gross outliers.
        view_weighting: after the first round, scale each board view's residuals by
            ``σ / σ_view`` (:func:`view_noise_scales`), i.e. weight the views by their own
            noise level (on rendered rigs 10 % of the views are 2-3x noisier than the median
            one: motion blur, steep boards).
        view_scale: (N,) residual scales to start from (the ``view_scale`` of a previous
            adjustment of the same observations, with its ``keep``); ``None`` = ones in the
            first round. Ignored without ``view_weighting``.
    """
    with _one_blas_thread():
        return _bundle_adjust(
            cam_params,
            free,
            frame_params,
            frames,
            obs,
            loss=loss,
            f_scale=f_scale,
            max_rounds=max_rounds,
            outlier_px=outlier_px,
            max_iter=max_iter,
            method=method,
            outlier_sigmas=outlier_sigmas,
            start_f_scale=start_f_scale,
            equal_focal=equal_focal,
            keep=keep,
            view_weighting=view_weighting,
            view_scale=view_scale,
        )


def _bundle_adjust(
    cam_params,
    free,
    frame_params,
    frames,
    obs,
    *,
    loss,
    f_scale,
    max_rounds,
    outlier_px,
    max_iter,
    method,
    outlier_sigmas,
    start_f_scale,
    equal_focal,
    keep,
    view_weighting,
    view_scale,
) -> BundleResult:
    if method not in ("lm", "scipy"):
        raise ValueError(f"unknown bundle-adjustment method {method!r}; expected lm or scipy")
    solver = _solve if method == "lm" else _solve_scipy
    t0 = time.perf_counter()
    cam = np.asarray(cam_params, np.float64).copy()
    fr = np.asarray(frame_params, np.float64).copy()
    tie = None
    if equal_focal is not None:
        tie = np.asarray(equal_focal, bool)
        if tie.shape != (cam.shape[0],):
            raise ValueError(f"equal_focal must have shape ({cam.shape[0]},), got {tie.shape}")
        if np.any(np.asarray(free)[tie, 1]):
            raise ValueError("a camera with equal_focal must have fy fixed (free[:, 1] False)")
        cam[tie, 1] = cam[tie, 0]
    uv, _ = project_observations(cam, fr, obs)
    e0 = np.linalg.norm(uv - obs.uv, axis=1)
    initial_rms = float(np.sqrt(np.mean(e0**2)))
    if keep is not None:
        keep = np.asarray(keep, bool).copy()
        if keep.shape != (len(obs),):
            raise ValueError(f"keep must have shape ({len(obs)},), got {keep.shape}")
    else:
        keep = np.ones(len(obs), bool)
        # grossly wrong initial detections would drag the first round
        if len(obs) > 20:
            keep &= e0 < max(50.0, 20 * np.median(e0))
    nfev = 0
    rounds = 0
    scale = float(start_f_scale) if f_scale is None else float(f_scale)
    groups = obs.cam.astype(np.int64) * (int(obs.frame.max(initial=0)) + 1) + obs.frame
    # per-observation residual scale (view weighting): from round 2, or given
    vscale = None
    if view_weighting and view_scale is not None:
        vscale = np.asarray(view_scale, np.float64)
        if vscale.shape != (len(obs),):
            raise ValueError(f"view_scale must have shape ({len(obs)},), got {vscale.shape}")
    for rounds in range(1, max_rounds + 1):  # noqa: B007
        sub = None if vscale is None else vscale[keep]
        cam, fr, n = solver(cam, free, fr, obs.subset(keep), loss, scale, max_iter, tie, sub)
        nfev += n
        uv, _ = project_observations(cam, fr, obs)
        err = np.linalg.norm(uv - obs.uv, axis=1)
        sigma = noise_sigma(err[keep])
        new_vscale = vscale
        if view_weighting and keep.any():
            # rejected detections get their view's scale too (they may come back)
            new_vscale = view_noise_scales(err, groups, sigma, use=keep)
        thr = max(outlier_px, outlier_sigmas * sigma)
        new_keep = err < thr
        new_scale = scale if f_scale is not None else max(MIN_F_SCALE, 2.0 * sigma)
        logger.info(
            "bundle round %d: RMS %.3f px over %d detections (noise σ %.3f px, loss scale "
            "%.3f px), %d rejected (> %.2f px)",
            rounds,
            float(np.sqrt(np.mean(err[keep] ** 2))),
            int(keep.sum()),
            sigma,
            scale,
            int((~new_keep).sum()),
            thr,
        )
        n_changed = int((new_keep != keep).sum())
        weights_settled = (vscale is None) == (new_vscale is None) and (
            vscale is None or np.max(np.abs(new_vscale - vscale)) <= 0.2
        )
        if (
            n_changed <= ROUND_TOL * len(obs)
            and abs(new_scale - scale) <= 0.2 * scale
            and weights_settled
        ):
            break  # the inliers and weights stay those the solution was fitted to
        keep, scale, vscale = new_keep, new_scale, new_vscale
    uv, _ = project_observations(cam, fr, obs)
    err = np.linalg.norm(uv - obs.uv, axis=1)
    return BundleResult(
        cam_params=cam,
        frame_params=fr,
        frames=np.asarray(frames),
        obs=obs,
        inliers=keep,
        errors=err,
        initial_rms=initial_rms,
        rounds=rounds,
        nfev=nfev,
        seconds=time.perf_counter() - t0,
        loss=loss,
        f_scale=scale,
        view_scale=vscale,
    )


def camera_covariance(result: BundleResult, free: np.ndarray) -> np.ndarray:
    """Marginal covariance (C, 15, 15) of every camera's parameters at the solution.

    Gauss-Newton approximation ``σ² S⁻¹`` from the reduced camera system (board poses
    eliminated) over the inlier detections, with the robust loss's weights; ``σ²`` is the
    weighted residual variance per degree of freedom. Local parameters: fx fy cx cy k1 k2 p1 p2
    k3 (absolute), rotation and translation (increments). Rows and columns of fixed
    parameters are zero.

    Args:
        result: a bundle-adjustment result.
        free: (C, 15) bool, the parameters that were optimised.
    """
    with _one_blas_thread():
        return _camera_covariance(result, free)


def _camera_covariance(result: BundleResult, free: np.ndarray) -> np.ndarray:
    cam, fr, obs = result.cam_params, result.frame_params, result.obs.subset(result.inliers)
    C, F = cam.shape[0], fr.shape[0]
    prob = _Problem(obs, C, F)  # (sorts the observations: prob.order)
    Rc, Rf = rodrigues(cam[:, 9:12]), rodrigues(fr[:, :3])
    r, cache = prob.residuals(cam[:, :9], Rc, cam[:, 12:15], Rf, fr[:, 3:])
    e = np.linalg.norm(r, axis=1)
    vs = result.view_scale
    w = _irls_weights(
        e, result.loss, result.f_scale, None if vs is None else vs[result.inliers][prob.order]
    )
    Hcc, Hff, Hcf, gc, gf = _normal_equations(prob, Rc, Rf, cache, r, w, free)
    S, _rhs, _ = _schur(Hcc, Hff + 1e-12 * np.eye(6), Hcf, gc, gf)
    dof = max(1, 2 * len(obs) - int(free.sum()) - 6 * F)
    s2 = float(np.sum(w * e**2) / dof)
    cov = s2 * np.linalg.pinv(S, hermitian=True)
    out = np.zeros((C, 15, 15))
    for c in range(C):
        blk = cov[c * 15 : (c + 1) * 15, c * 15 : (c + 1) * 15]
        m = free[c]
        out[c][np.ix_(m, m)] = blk[np.ix_(m, m)]
    return out


def board_point_offsets(
    result: BundleResult, point_ids: np.ndarray, n_points: int, min_obs: int = 100
) -> np.ndarray:
    """In-plane corrections (P, 2) mm of the board points that best explain the residuals.

    A printed board's points are not exactly where the design puts them (print scaling and
    paper), and a detector locates each corner with a bias of its own (the neighbouring marker
    pattern differs from corner to corner); both are the same in every view. For each board
    point seen at least ``min_obs`` times among the inliers, the weighted least-squares shift
    of the point in the board plane that best explains its reprojection residuals (cameras
    and board poses held) is returned. Shifts that a board pose or the board's scale would
    absorb (common translation, in-plane rotation, uniform scale about the points' centroid)
    are projected out, so the board keeps its position, orientation and printed size. Points
    seen fewer times (and all points when fewer than 4 qualify) get 0.

    Args:
        result: a bundle-adjustment result whose ``obs.point`` are the current board points.
        point_ids: (N,) board point index of every observation (same order as ``result.obs``).
        n_points: number of board points P.
        min_obs: inlier observations a point needs to be corrected. With few views the
            correction trades against the intrinsics (on the Bouguet stereo set, 28 views per
            corner, it moved a principal point by 4 px, 3 times Bouguet's 3σ uncertainty).
    """
    b = result
    keep = b.inliers
    o = b.obs.subset(keep)
    ids = np.asarray(point_ids)[keep]
    out = np.zeros((n_points, 2))
    if len(o) == 0:
        return out
    uv, _ = project_observations(b.cam_params, b.frame_params, o)
    r = o.uv - uv
    vs = None if b.view_scale is None else b.view_scale[keep]
    w = _irls_weights(np.linalg.norm(r, axis=1), b.loss, b.f_scale, vs)
    h = 1e-2  # mm; the projection is linear over this
    J = np.zeros((len(o), 2, 2))  # d uv / d (board x, board y)
    for k in range(2):
        pt = o.point.copy()
        pt[:, k] += h
        uvk, _ = project_observations(
            b.cam_params, b.frame_params, Observations(o.cam, o.frame, pt, o.uv)
        )
        J[:, :, k] = (uvk - uv) / h
    A = np.zeros((n_points, 2, 2))
    g = np.zeros((n_points, 2))
    np.add.at(A, ids, w[:, None, None] * np.einsum("nki,nkj->nij", J, J))
    np.add.at(g, ids, w[:, None] * np.einsum("nki,nk->ni", J, r))
    count = np.bincount(ids, minlength=n_points)
    ok = count >= min_obs
    if ok.sum() < 4:
        return out
    out[ok] = np.linalg.solve(A[ok], g[ok][..., None])[..., 0]
    # project out translation, in-plane rotation and scale of the corrected points
    pts = np.unique(np.c_[ids, o.point[:, :2]], axis=0)
    xy = np.zeros((n_points, 2))
    xy[pts[:, 0].astype(int)] = pts[:, 1:]
    x = xy[ok] - xy[ok].mean(axis=0)
    m = int(ok.sum())
    basis = np.stack(
        [
            np.tile([1.0, 0.0], m),
            np.tile([0.0, 1.0], m),
            np.stack([-x[:, 1], x[:, 0]], axis=1).ravel(),
            x.ravel(),
        ],
        axis=1,
    )
    q, _ = np.linalg.qr(basis)
    v = out[ok].ravel()
    out[ok] = (v - q @ (q.T @ v)).reshape(m, 2)
    return out
