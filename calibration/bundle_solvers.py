"""The bundle adjustment's two solvers for one round (fixed inliers, loss scale and weights).

:func:`solve_lm` is Levenberg-Marquardt with analytic Jacobians and the Schur complement
over the board poses; :func:`solve_scipy` is ``scipy.optimize.least_squares`` with a sparse
Jacobian pattern (slower; kept as a cross-check).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from freipose.calibration.bundle_problem import (
    Observations,
    Problem,
    Projection,
    normal_equations,
    project_observations,
    schur,
)
from freipose.calibration.params import (
    CAM_PARAMS,
    FRAME_PARAMS,
    FRAME_RVEC,
    FRAME_TVEC,
    INTRINSICS,
    RVEC,
    TVEC,
)
from freipose.calibration.robust import irls_weights, robust_cost
from freipose.geometry.transforms import matrix_to_rodrigues, rodrigues

__all__ = ["REL_TOL", "Solution", "solve_lm", "solve_scipy"]

# Levenberg-Marquardt stops when a step lowers the cost by less than this fraction: the cost
# is ~σ² per residual, and moving a parameter by one standard error changes it by ~σ², i.e.
# ~1 / (2 N) of it, far more than this tolerance
REL_TOL = 1e-6
# damping attempts per Levenberg-Marquardt iteration before it gives up
_MAX_DAMPING_TRIES = 12


@dataclass(frozen=True)
class Solution:
    """A solver's result.

    Attributes:
        cam_params: (C, 15) camera rows.
        frame_params: (F, 6) board-pose rows.
        nfev: residual evaluations.
    """

    cam_params: np.ndarray
    frame_params: np.ndarray
    nfev: int


@dataclass(frozen=True)
class _State:
    """The Levenberg-Marquardt state.

    Attributes:
        intr: (C, 9) intrinsics.
        Rc: (C, 3, 3) world→camera rotations.
        tc: (C, 3) world→camera translations (mm).
        Rf: (F, 3, 3) board→world rotations.
        tf: (F, 3) board→world translations (mm).
    """

    intr: np.ndarray
    Rc: np.ndarray
    tc: np.ndarray
    Rf: np.ndarray
    tf: np.ndarray


@dataclass(frozen=True)
class _Evaluation:
    """Cost, residuals (N, 2), error norms (N,) and the projection of one state."""

    cost: float
    r: np.ndarray
    e: np.ndarray
    pr: Projection


def _start_state(cam0: np.ndarray, frame0: np.ndarray, tie: np.ndarray | None) -> _State:
    """The state of the parameter rows ``cam0`` (C, 15) and ``frame0`` (F, 6)."""
    intr = cam0[:, INTRINSICS].copy()
    if tie is not None:
        intr[tie, 1] = intr[tie, 0]
    return _State(
        intr,
        rodrigues(cam0[:, RVEC]),
        cam0[:, TVEC].copy(),
        rodrigues(frame0[:, FRAME_RVEC]),
        frame0[:, FRAME_TVEC].copy(),
    )


def _damped_step(
    s: _State,
    ne_blocks: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    lam: float,
    freef: np.ndarray,
    tie: np.ndarray | None,
) -> _State | None:
    """The state after one step of the damped normal equations, None if ``S`` is singular.

    Args:
        s: the current state.
        ne_blocks: ``(Hcc, Hff, Hcf, gc, gf)`` of :func:`normal_equations` at ``s``.
        lam: the damping factor.
        freef: (C, 15) 1.0 for the optimised camera parameters, else 0.0.
        tie: (C,) bool, cameras whose fy is tied to fx, or None.

    Returns:
        The new state, or None.
    """
    Hcc, Hff, Hcf, gc, gf = ne_blocks
    C = Hcc.shape[0]
    Hcc_d = Hcc.copy()
    dc = np.einsum("cii->ci", Hcc_d)
    dc += lam * np.maximum(dc, 1e-9)
    Hff_d = Hff.copy()
    df = np.einsum("fii->fi", Hff_d)
    df += lam * np.maximum(df, 1e-9) + 1e-12
    red = schur(Hcc_d, Hff_d, Hcf, gc, gf)
    try:
        dcam = np.linalg.solve(red.S, red.rhs)
    except np.linalg.LinAlgError:
        return None
    dcam = dcam.reshape(C, CAM_PARAMS) * freef
    dfr = -np.einsum("fij,fj->fi", red.Hff_inv, gf + np.einsum("cfij,ci->fj", Hcf, dcam))
    n_intr = s.intr + dcam[:, INTRINSICS]
    if tie is not None:
        n_intr[tie, 1] = n_intr[tie, 0]
    # left rotation updates: of Rc acting on (Rc Xw), of Rf on (Rf X); t is updated additively
    return _State(
        n_intr,
        rodrigues(dcam[:, RVEC]) @ s.Rc,
        s.tc + dcam[:, TVEC] + 0.0,
        rodrigues(dfr[:, FRAME_RVEC]) @ s.Rf,
        s.tf + dfr[:, FRAME_TVEC],
    )


def _to_params(s: _State, cam0: np.ndarray, frame0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera rows (C, 15) and board-pose rows (F, 6) of a state (shaped like the start)."""
    cam = np.zeros_like(cam0)
    cam[:, INTRINSICS] = s.intr
    cam[:, RVEC] = np.stack([matrix_to_rodrigues(R) for R in s.Rc])
    cam[:, TVEC] = s.tc
    fr = np.zeros_like(frame0)
    F = frame0.shape[0]
    fr[:, FRAME_RVEC] = np.stack([matrix_to_rodrigues(R) for R in s.Rf]) if F else np.zeros((0, 3))
    fr[:, FRAME_TVEC] = s.tf
    return cam, fr


def solve_lm(
    cam0: np.ndarray,
    free: np.ndarray,
    frame0: np.ndarray,
    obs: Observations,
    loss: str,
    f_scale: float,
    max_iter: int,
    tie: np.ndarray | None = None,
    scale: np.ndarray | None = None,
) -> Solution:
    """Levenberg-Marquardt with the Schur complement over the board poses.

    Args:
        cam0: (C, 15) start camera rows.
        free: (C, 15) bool, the optimised camera parameters.
        frame0: (F, 6) start board-pose rows.
        obs: the observations (N).
        loss: robust loss name.
        f_scale: robust loss scale (px).
        max_iter: most iterations.
        tie: (C,) bool, cameras whose fy is tied to fx, or None.
        scale: (N,) factors each observation's residual is multiplied by (per-view noise
            weighting), or None.

    Returns:
        The refined rows and the number of residual evaluations.
    """
    C, F = cam0.shape[0], frame0.shape[0]
    prob = Problem(obs, C, F)
    if scale is not None:
        scale = np.asarray(scale)[prob.order]  # the problem sorts the observations
    state = _start_state(cam0, frame0, tie)
    freef = free.astype(float)

    def evaluate(s: _State) -> _Evaluation:
        r, pr = prob.residuals(s.intr, s.Rc, s.tc, s.Rf, s.tf)
        e = np.linalg.norm(r, axis=1)
        return _Evaluation(robust_cost(e if scale is None else e * scale, loss, f_scale), r, e, pr)

    ev = evaluate(state)
    lam = 1e-3
    nfev = 1
    for _it in range(1, max_iter + 1):
        w = irls_weights(ev.e, loss, f_scale, scale)
        ne = normal_equations(prob, state.Rc, state.Rf, ev.pr, ev.r, w, free, tie)
        blocks = (ne.Hcc, ne.Hff, ne.Hcf, ne.gc, ne.gf)
        improved = False
        for _ in range(_MAX_DAMPING_TRIES):
            new = _damped_step(state, blocks, lam, freef, tie)
            if new is None:
                lam *= 10
                continue
            n_ev = evaluate(new)
            nfev += 1
            if np.isfinite(n_ev.cost) and n_ev.cost < ev.cost:
                rel = (ev.cost - n_ev.cost) / max(ev.cost, 1e-300)
                state, ev = new, n_ev
                lam = max(lam / 3, 1e-9)
                improved = True
                break
            lam *= 4
        if not improved or rel < REL_TOL:
            break
    cam, fr = _to_params(state, cam0, frame0)
    return Solution(cam, fr, nfev)


def _sparsity(obs: Observations, cam_cols: np.ndarray, n_cam_free: int, F: int):
    """The sparse Jacobian pattern (2N, free camera parameters + 6F) for scipy."""
    from scipy.sparse import coo_matrix

    N = len(obs)
    rows, cols = [], []
    r0 = 2 * np.arange(N)
    cc = cam_cols[obs.cam]  # (N, 15), -1 if fixed
    for k in range(CAM_PARAMS):
        ok = cc[:, k] >= 0
        for d in (0, 1):
            rows.append(r0[ok] + d)
            cols.append(cc[ok, k])
    for k in range(FRAME_PARAMS):
        for d in (0, 1):
            rows.append(r0 + d)
            cols.append(n_cam_free + FRAME_PARAMS * obs.frame + k)
    rows_a = np.concatenate(rows)
    cols_a = np.concatenate(cols)
    data = np.ones(len(rows_a), dtype=np.int8)
    shape = (2 * N, n_cam_free + FRAME_PARAMS * F)
    return coo_matrix((data, (rows_a, cols_a)), shape=shape).tocsr()


def solve_scipy(
    cam0: np.ndarray,
    free: np.ndarray,
    frame0: np.ndarray,
    obs: Observations,
    loss: str,
    f_scale: float,
    max_iter: int,
    tie: np.ndarray | None = None,
    scale: np.ndarray | None = None,
) -> Solution:
    """``scipy.optimize.least_squares`` (TRF, LSMR) with a finite-difference sparse Jacobian.

    Args:
        cam0: (C, 15) start camera rows.
        free: (C, 15) bool, the optimised camera parameters.
        frame0: (F, 6) start board-pose rows.
        obs: the observations (N).
        loss: robust loss name.
        f_scale: robust loss scale (px).
        max_iter: most iterations (scipy evaluates at most twice as often).
        tie: (C,) bool, cameras whose fy is tied to fx, or None.
        scale: (N,) factors each observation's residual is multiplied by, or None.

    Returns:
        The refined rows and the number of residual evaluations.
    """
    from scipy.optimize import least_squares

    C, F = cam0.shape[0], frame0.shape[0]
    cam_cols = np.full((C, CAM_PARAMS), -1, dtype=np.int64)
    cam_cols[free] = np.arange(int(free.sum()))
    n_cam_free = int(free.sum())

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cam = cam0.copy()
        cam[free] = x[:n_cam_free]
        if tie is not None:
            cam[tie, 1] = cam[tie, 0]
        return cam, x[n_cam_free:].reshape(F, FRAME_PARAMS)

    def fun(x: np.ndarray) -> np.ndarray:
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
    return Solution(cam, fr, int(res.nfev))
