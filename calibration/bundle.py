"""Multi-camera bundle adjustment of intrinsics, distortion, extrinsics and board poses.

Rounds of a solver (:mod:`freipose.calibration.bundle_solvers`: Levenberg-Marquardt with
analytic Jacobians and the Schur complement over the per-frame board poses, or
``scipy.optimize.least_squares`` as a cross-check) with a robust loss (iteratively
reweighted, :mod:`freipose.calibration.robust`), and outlier rejection between rounds, in which
every board view's residuals are also weighted by its own noise level (views with motion blur or
a steep board are noisier than the rest). The parameter rows are laid out as in
:mod:`freipose.calibration.params`; the problem itself is
:mod:`freipose.calibration.bundle_problem`.
"""

from __future__ import annotations

import logging
import time
from contextlib import AbstractContextManager
from dataclasses import dataclass

import numpy as np

from freipose.calibration.bundle_problem import (
    Observations,
    Problem,
    normal_equations,
    project_observations,
    schur,
)
from freipose.calibration.bundle_solvers import Solution, solve_lm, solve_scipy
from freipose.calibration.intrinsics import CalibrationError
from freipose.calibration.params import (
    CAM_PARAMS,
    FRAME_PARAMS,
    FRAME_RVEC,
    FRAME_TVEC,
    INTRINSICS,
    RVEC,
    TVEC,
)
from freipose.calibration.robust import (
    camera_noise_sigmas,
    irls_weights,
    noise_sigma,
    view_noise_scales,
)
from freipose.geometry.transforms import rodrigues

logger = logging.getLogger(__name__)

__all__ = [
    "BundleResult",
    "board_point_offsets",
    "bundle_adjust",
    "camera_covariance",
]

MIN_F_SCALE = 0.05  # px: floor of the estimated robust-loss scale
# outlier-rejection rounds stop when at most this fraction of the detections change status
# (and the loss scale and the view weights change by at most _SETTLED_CHANGE)
ROUND_TOL = 1e-3
_SETTLED_CHANGE = 0.2
# with more detections than this, grossly wrong ones are dropped before the first round
_MIN_OBS_GROSS = 20


def _one_blas_thread() -> AbstractContextManager:
    """Context limiting BLAS to one thread.

    The solver's matrices are small (cameras x 15 squared, batches of 15 x 24 blocks), where
    BLAS threads cost more than they save. (``threadpoolctl`` comes with scikit-learn.)
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - scikit-learn depends on it
        from contextlib import nullcontext

        return nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


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
        initial_rms: RMS error (px) of all observations at the start.
        rounds: solve / reject rounds run.
        nfev: residual evaluations of all rounds.
        seconds: wall time of the adjustment.
        loss: the robust loss.
        f_scale: the robust loss's scale (px) of the last round.
        view_scale: (N,) the factor every observation's residual was scaled by in the last
            round (``σ / σ_view``, the global over its board view's noise level), or None
            without view weighting.
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
        outlier_px: the smallest outlier threshold (px), see ``outlier_sigmas``.
        max_iter: most solver iterations per round.
        method: ``"lm"`` (Levenberg-Marquardt with Schur complement, analytic Jacobian) or
            ``"scipy"`` (``least_squares`` with a sparse finite-difference Jacobian).
        outlier_sigmas: a detection is rejected when its error exceeds
            ``max(outlier_px, outlier_sigmas * σ_c)`` after a round, where ``σ_c`` is its
            camera's own noise level (:func:`~freipose.calibration.robust.camera_noise_sigmas`:
            from the camera's median error over its inliers), so that a camera whose corners
            are honestly noisier keeps them while corners off by a marker or a square (wrong
            ids, mirrored views) are still removed.
        start_f_scale: the loss scale (px) of the first round when ``f_scale`` is None.
        equal_focal: (C,) bool, cameras whose fy is tied to fx (square pixels; their
            ``free[:, 1]`` must be False); ``None`` = none.
        keep: (N,) bool, the detections to start from (e.g. the inliers of a previous
            adjustment of the same observations); ``None`` = all but gross outliers.
        view_weighting: after the first round, scale each board view's residuals by
            ``σ / σ_view`` (:func:`~freipose.calibration.robust.view_noise_scales`), i.e.
            weight the views by their own noise level.
        view_scale: (N,) residual scales to start from (the ``view_scale`` of a previous
            adjustment of the same observations, with its ``keep``); ``None`` = ones in the
            first round. Ignored without ``view_weighting``.

    Returns:
        The refined parameters and diagnostics.

    Raises:
        CalibrationError: an unknown ``method``.
        ValueError: ``equal_focal``, ``keep`` or ``view_scale`` of the wrong shape, or a tied
            camera with a free fy.
    """
    with _one_blas_thread():
        return _bundle_adjust(
            cam_params,
            free,
            frame_params,
            frames,
            obs,
            _Settings(
                loss=loss,
                f_scale=f_scale,
                max_rounds=max_rounds,
                outlier_px=outlier_px,
                max_iter=max_iter,
                method=method,
                outlier_sigmas=outlier_sigmas,
                start_f_scale=start_f_scale,
                view_weighting=view_weighting,
            ),
            equal_focal=equal_focal,
            keep=keep,
            view_scale=view_scale,
        )


@dataclass(frozen=True)
class _Settings:
    """The scalar options of :func:`bundle_adjust` (see there)."""

    loss: str
    f_scale: float | None
    max_rounds: int
    outlier_px: float
    max_iter: int
    method: str
    outlier_sigmas: float
    start_f_scale: float
    view_weighting: bool


@dataclass(frozen=True)
class _Start:
    """The checked starting point of the rounds.

    Attributes:
        cam: (C, 15) camera rows (fy = fx for tied cameras).
        fr: (F, 6) board-pose rows.
        tie: (C,) bool cameras whose fy is tied to fx, or None.
        keep: (N,) bool, the detections of the first round.
        vscale: (N,) residual scales of the first round, or None.
        initial_rms: RMS error (px) of all detections at the start.
    """

    cam: np.ndarray
    fr: np.ndarray
    tie: np.ndarray | None
    keep: np.ndarray
    vscale: np.ndarray | None
    initial_rms: float


def _start(
    cam_params: np.ndarray,
    free: np.ndarray,
    frame_params: np.ndarray,
    obs: Observations,
    equal_focal: np.ndarray | None,
    keep: np.ndarray | None,
    view_scale: np.ndarray | None,
    view_weighting: bool,
) -> _Start:
    """Check the inputs and set up the first round (see :func:`bundle_adjust`)."""
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
        if len(obs) > _MIN_OBS_GROSS:
            keep &= e0 < max(50.0, 20 * np.median(e0))
    vscale = None
    if view_weighting and view_scale is not None:
        vscale = np.asarray(view_scale, np.float64)
        if vscale.shape != (len(obs),):
            raise ValueError(f"view_scale must have shape ({len(obs)},), got {vscale.shape}")
    return _Start(cam, fr, tie, keep, vscale, initial_rms)


@dataclass(frozen=True)
class _Rejection:
    """What a round's solution implies for the next round.

    Attributes:
        err: (N,) error norms (px) of all detections.
        sigma: the inliers' per-axis noise σ (px).
        thr: (C,) every camera's outlier threshold (px).
        keep: (N,) bool, the detections below ``thr``.
        scale: the next loss scale (px).
        vscale: (N,) the next residual scales, or None.
    """

    err: np.ndarray
    sigma: float
    thr: np.ndarray
    keep: np.ndarray
    scale: float
    vscale: np.ndarray | None


def _reject(
    sol: Solution,
    obs: Observations,
    keep: np.ndarray,
    scale: float,
    vscale: np.ndarray | None,
    groups: np.ndarray,
    opt: _Settings,
) -> _Rejection:
    """Errors, noise level, inliers, loss scale and view weights after a round's solution."""
    uv, _ = project_observations(sol.cam_params, sol.frame_params, obs)
    err = np.linalg.norm(uv - obs.uv, axis=1)
    sigma = noise_sigma(err[keep])
    new_vscale = vscale
    if opt.view_weighting and keep.any():
        # rejected detections get their view's scale too (they may come back)
        new_vscale = view_noise_scales(err, groups, sigma, use=keep)
    n_cams = int(sol.cam_params.shape[0])
    sigmas = camera_noise_sigmas(err, obs.cam, n_cams, sigma, keep)
    thr = np.maximum(opt.outlier_px, opt.outlier_sigmas * sigmas)
    new_scale = scale if opt.f_scale is not None else max(MIN_F_SCALE, 2.0 * sigma)
    return _Rejection(err, sigma, thr, err < thr[obs.cam], new_scale, new_vscale)


def _settled(
    keep: np.ndarray, scale: float, vscale: np.ndarray | None, nxt: _Rejection, n: int
) -> bool:
    """Whether the inliers, the loss scale and the view weights stay (nearly) the same."""
    n_changed = int((nxt.keep != keep).sum())
    weights_settled = (vscale is None) == (nxt.vscale is None) and (
        vscale is None or np.max(np.abs(nxt.vscale - vscale)) <= _SETTLED_CHANGE
    )
    return (
        n_changed <= ROUND_TOL * n
        and abs(nxt.scale - scale) <= _SETTLED_CHANGE * scale
        and weights_settled
    )


def _bundle_adjust(
    cam_params: np.ndarray,
    free: np.ndarray,
    frame_params: np.ndarray,
    frames: np.ndarray,
    obs: Observations,
    opt: _Settings,
    *,
    equal_focal: np.ndarray | None,
    keep: np.ndarray | None,
    view_scale: np.ndarray | None,
) -> BundleResult:
    """:func:`bundle_adjust` (BLAS limits already set) with its scalar options in ``opt``."""
    if opt.method not in ("lm", "scipy"):
        raise CalibrationError(
            f"unknown bundle-adjustment method {opt.method!r}; expected lm or scipy"
        )
    solver = solve_lm if opt.method == "lm" else solve_scipy
    t0 = time.perf_counter()
    st = _start(
        cam_params, free, frame_params, obs, equal_focal, keep, view_scale, opt.view_weighting
    )
    cam, fr, keep, vscale = st.cam, st.fr, st.keep, st.vscale
    nfev = 0
    rounds = 0
    scale = float(opt.start_f_scale) if opt.f_scale is None else float(opt.f_scale)
    groups = obs.cam.astype(np.int64) * (int(obs.frame.max(initial=0)) + 1) + obs.frame
    for rounds in range(1, opt.max_rounds + 1):  # noqa: B007
        sub = None if vscale is None else vscale[keep]
        sol = solver(cam, free, fr, obs.subset(keep), opt.loss, scale, opt.max_iter, st.tie, sub)
        cam, fr = sol.cam_params, sol.frame_params
        nfev += sol.nfev
        nxt = _reject(sol, obs, keep, scale, vscale, groups, opt)
        logger.debug(
            "bundle round %d: RMS %.3f px over %d detections (noise σ %.3f px, loss scale "
            "%.3f px), %d rejected (> %s px)",
            rounds,
            float(np.sqrt(np.mean(nxt.err[keep] ** 2))),
            int(keep.sum()),
            nxt.sigma,
            scale,
            int((~nxt.keep).sum()),
            " / ".join(f"{t:.2f}" for t in nxt.thr),
        )
        if _settled(keep, scale, vscale, nxt, len(obs)):
            break  # the inliers and weights stay those the solution was fitted to
        keep, scale, vscale = nxt.keep, nxt.scale, nxt.vscale
    uv, _ = project_observations(cam, fr, obs)
    err = np.linalg.norm(uv - obs.uv, axis=1)
    return BundleResult(
        cam_params=cam,
        frame_params=fr,
        frames=np.asarray(frames),
        obs=obs,
        inliers=keep,
        errors=err,
        initial_rms=st.initial_rms,
        rounds=rounds,
        nfev=nfev,
        seconds=time.perf_counter() - t0,
        loss=opt.loss,
        f_scale=scale,
        view_scale=vscale,
    )


def camera_covariance(
    result: BundleResult, free: np.ndarray, tie: np.ndarray | None = None
) -> np.ndarray:
    """Marginal covariance of every camera's parameters at the solution.

    Gauss-Newton approximation ``σ² S⁻¹`` from the reduced camera system (board poses
    eliminated) over the inlier detections, with the robust loss's weights; ``σ²`` is the
    weighted residual variance per degree of freedom. Local parameters: fx fy cx cy k1 k2 p1 p2
    k3 (absolute), rotation and translation (increments). Rows and columns of fixed
    parameters are zero; a tied fy (``tie``) is fx's row and column.

    Args:
        result: a bundle-adjustment result.
        free: (C, 15) bool, the parameters that were optimised.
        tie: (C,) bool, cameras whose fy was tied to fx (their fx moves both focal lengths);
            ``None``: none.

    Returns:
        (C, 15, 15) covariances.
    """
    with _one_blas_thread():
        return _camera_covariance(result, free, tie)


def _camera_covariance(
    result: BundleResult, free: np.ndarray, tie: np.ndarray | None
) -> np.ndarray:
    """:func:`camera_covariance` (BLAS limits already set)."""
    cam, fr, obs = result.cam_params, result.frame_params, result.obs.subset(result.inliers)
    C, F = cam.shape[0], fr.shape[0]
    nc = CAM_PARAMS
    prob = Problem(obs, C, F)  # (sorts the observations: prob.order)
    Rc, Rf = rodrigues(cam[:, RVEC]), rodrigues(fr[:, FRAME_RVEC])
    r, pr = prob.residuals(cam[:, INTRINSICS], Rc, cam[:, TVEC], Rf, fr[:, FRAME_TVEC])
    e = np.linalg.norm(r, axis=1)
    vs = result.view_scale
    w = irls_weights(
        e, result.loss, result.f_scale, None if vs is None else vs[result.inliers][prob.order]
    )
    ne = normal_equations(prob, Rc, Rf, pr, r, w, free, tie)
    S = schur(ne.Hcc, ne.Hff + 1e-12 * np.eye(FRAME_PARAMS), ne.Hcf, ne.gc, ne.gf).S
    dof = max(1, 2 * len(obs) - int(free.sum()) - FRAME_PARAMS * F)
    s2 = float(np.sum(w * e**2) / dof)
    cov = s2 * np.linalg.pinv(S, hermitian=True)
    out = np.zeros((C, nc, nc))
    for c in range(C):
        blk = cov[c * nc : (c + 1) * nc, c * nc : (c + 1) * nc]
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
        min_obs: inlier observations a point needs to be corrected (with few views the
            correction trades against the intrinsics).

    Returns:
        (P, 2) in-plane shifts of the board points (mm).
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
    w = irls_weights(np.linalg.norm(r, axis=1), b.loss, b.f_scale, vs)
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
