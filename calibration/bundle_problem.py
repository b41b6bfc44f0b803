"""The bundle adjustment's problem: observations, residuals, analytic Jacobians, normal equations.

Each residual depends on one camera (15 parameters, see :mod:`freipose.calibration.params`)
and one board pose (6 parameters), so the Gauss-Newton normal equations are block sparse:
:func:`normal_equations` sums them per (camera, board pose) pair and :func:`schur` reduces
them to a small dense system in the camera parameters (the board poses eliminated).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from freipose.calibration.params import (
    CAM_PARAMS,
    DIST,
    FOCAL,
    FRAME_PARAMS,
    FRAME_RVEC,
    FRAME_TVEC,
    INTRINSICS,
    RVEC,
    TVEC,
)
from freipose.geometry.distortion import DistortionTerms, distortion_jacobian, distortion_terms
from freipose.geometry.transforms import rodrigues

__all__ = [
    "NormalEquations",
    "Observations",
    "Problem",
    "Projection",
    "ReducedSystem",
    "Segments",
    "normal_equations",
    "project_observations",
    "schur",
]

# depths below this (mm, in absolute value) are clamped for the division by the depth
_MIN_DEPTH = 1e-9


@dataclass(frozen=True)
class Observations:
    """A flat list of board-point detections.

    Attributes:
        cam: (N,) camera index of each detection.
        frame: (N,) board-pose index of each detection.
        point: (N, 3) the detected board point in board coordinates (mm).
        uv: (N, 2) the detected pixel.
    """

    cam: np.ndarray
    frame: np.ndarray
    point: np.ndarray
    uv: np.ndarray

    def __len__(self) -> int:
        return int(self.cam.shape[0])

    def subset(self, keep: np.ndarray) -> Observations:
        """The detections selected by ``keep`` ((N,) bool mask or index array)."""
        return Observations(self.cam[keep], self.frame[keep], self.point[keep], self.uv[keep])


@dataclass(frozen=True)
class Projection:
    """Every observation's board point projected, with the intermediate values.

    Attributes:
        Xw: (N, 3) the point in the world (mm).
        Xc: (N, 3) the point in the camera (mm).
        z: (N,) its depth, clamped away from 0 (``_MIN_DEPTH``) for the division.
        x: (N,) normalized x (``Xc[:, 0] / z``).
        y: (N,) normalized y.
        intr: (N, 9) the observing camera's intrinsics.
        terms: the distortion polynomial's parts at ``(x, y)``.
        uv: (N, 2) the projected pixels.
    """

    Xw: np.ndarray
    Xc: np.ndarray
    z: np.ndarray
    x: np.ndarray
    y: np.ndarray
    intr: np.ndarray
    terms: DistortionTerms
    uv: np.ndarray


def _project(
    intr: np.ndarray,
    Rc: np.ndarray,
    tc: np.ndarray,
    Rf: np.ndarray,
    tf: np.ndarray,
    obs: Observations,
) -> Projection:
    """Project the observations' board points.

    Args:
        intr: (C, 9) intrinsics ``fx fy cx cy k1 k2 p1 p2 k3``.
        Rc: (C, 3, 3) world→camera rotations.
        tc: (C, 3) world→camera translations (mm).
        Rf: (F, 3, 3) board→world rotations.
        tf: (F, 3) board→world translations (mm).
        obs: the observations.

    Returns:
        The projection and its intermediate values.
    """
    fi, ci = obs.frame, obs.cam
    Xw = np.einsum("nij,nj->ni", Rf[fi], obs.point) + tf[fi]
    Xc = np.einsum("nij,nj->ni", Rc[ci], Xw) + tc[ci]
    z = Xc[:, 2]
    zs = np.where(np.abs(z) < _MIN_DEPTH, _MIN_DEPTH, z)
    x, y = Xc[:, 0] / zs, Xc[:, 1] / zs
    p = intr[ci]
    t = distortion_terms(x, y, p[:, DIST])
    uv = np.stack([p[:, 0] * t.xd + p[:, 2], p[:, 1] * t.yd + p[:, 3]], axis=1)
    return Projection(Xw, Xc, zs, x, y, p, t, uv)


def project_observations(
    cam_params: np.ndarray, frame_params: np.ndarray, obs: Observations
) -> tuple[np.ndarray, np.ndarray]:
    """Project every observation's board point.

    Args:
        cam_params: (C, 15) camera rows ``fx fy cx cy k1 k2 p1 p2 k3 rvec t`` (world→camera).
        frame_params: (F, 6) board-pose rows ``rvec t`` (board→world).
        obs: the observations.

    Returns:
        (N, 2) pixels and (N,) depth in the camera (mm).
    """
    Rf = rodrigues(frame_params[:, FRAME_RVEC])
    Rc = rodrigues(cam_params[:, RVEC])
    pr = _project(
        cam_params[:, INTRINSICS],
        Rc,
        cam_params[:, TVEC],
        Rf,
        frame_params[:, FRAME_TVEC],
        obs,
    )
    return pr.uv, pr.Xc[:, 2]


def _run_starts(keys: np.ndarray) -> np.ndarray:
    """Indices (R,) where the runs of equal values of a sorted key array (K,) start."""
    if len(keys) == 0:
        return np.zeros(0, np.int64)
    return np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])


class Segments:
    """Sums of consecutive rows that share a key.

    Calling it with ``x`` (K, ...) returns (n, ...): row ``k`` is the sum of the rows of
    ``x`` whose key is ``k`` (zero for keys that do not occur).

    Args:
        keys: (K,) sorted keys in ``[0, n)``.
        n: the number of keys.
    """

    def __init__(self, keys: np.ndarray, n: int):
        self.n = n
        self.starts = _run_starts(keys)
        self.keys = keys[self.starts]

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Segment sums (n, ...) of the rows of ``x`` (K, ...)."""
        out = np.zeros((self.n,) + x.shape[1:])
        if len(self.starts):
            out[self.keys] = np.add.reduceat(x, self.starts, axis=0)
        return out


class Problem:
    """Residuals and analytic Jacobians with local (left-multiplied) rotation updates.

    State: intrinsics (C, 9), camera rotations (C, 3, 3), translations (C, 3), board rotations
    (F, 3, 3), translations (F, 3). A camera's 15 local parameters are fx fy cx cy k1 k2 p1 p2
    k3, δrot (3), δt (3); a board's 6 are δrot (3), δt (3). The problem sorts the observations
    by camera and board pose (``order`` maps its rows to the given ones).

    Args:
        obs: the observations (N).
        C: number of cameras.
        F: number of board poses.
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
        self.cam_sum = Segments(self.pair_cam, C)
        self.by_frame = np.argsort(self.pair_frame, kind="stable")
        self.frame_sum = Segments(self.pair_frame[self.by_frame], F)
        self.C, self.F = C, F

    def residuals(
        self, intr: np.ndarray, Rc: np.ndarray, tc: np.ndarray, Rf: np.ndarray, tf: np.ndarray
    ) -> tuple[np.ndarray, Projection]:
        """Reprojection residuals of the (sorted) observations.

        Args:
            intr: (C, 9) intrinsics.
            Rc: (C, 3, 3) world→camera rotations.
            tc: (C, 3) world→camera translations.
            Rf: (F, 3, 3) board→world rotations.
            tf: (F, 3) board→world translations.

        Returns:
            (N, 2) projected minus detected pixels, and the projection (for
            :meth:`jacobians`).
        """
        pr = _project(intr, Rc, tc, Rf, tf, self.obs)
        return pr.uv - self.obs.uv, pr

    def jacobians(
        self, Rc: np.ndarray, Rf: np.ndarray, pr: Projection
    ) -> tuple[np.ndarray, np.ndarray]:
        """Jacobians of the residuals by the local camera and board-pose parameters.

        Args:
            Rc: (C, 3, 3) world→camera rotations.
            Rf: (F, 3, 3) board→world rotations.
            pr: the projection returned by :meth:`residuals` for the same state.

        Returns:
            ``Jc`` (N, 2, 15) by the observing camera's parameters and ``Jf`` (N, 2, 6) by
            the board pose's.
        """
        o = self.obs
        x, y, z, p, t = pr.x, pr.y, pr.z, pr.intr, pr.terms
        N = len(o)
        Jc = np.zeros((N, 2, CAM_PARAMS))
        Jc[:, 0, 0] = t.xd
        Jc[:, 1, 1] = t.yd
        Jc[:, 0, 2] = 1.0
        Jc[:, 1, 3] = 1.0
        dj = distortion_jacobian(x, y, p[:, DIST], t)
        f = p[:, FOCAL][:, :, None]
        Jc[:, :, DIST] = f * dj.d_dist
        A = f * dj.d_xy  # d uv / d (x, y)
        Bn = np.zeros((N, 2, 3))  # d(x, y)/d Xc
        Bn[:, 0, 0] = 1 / z
        Bn[:, 1, 1] = 1 / z
        Bn[:, 0, 2] = -x / z
        Bn[:, 1, 2] = -y / z
        D = A @ Bn  # (N, 2, 3) d uv / d Xc
        # the rotation perturbation acts on Rc Xw: d uv / d δrot = -D [Rc Xw]x, whose rows are
        # (Rc Xw) x (rows of D)
        RcXw = np.einsum("nij,nj->ni", Rc[o.cam], pr.Xw)
        Jc[:, :, RVEC] = np.cross(RcXw[:, None, :], D)
        Jc[:, :, TVEC] = D
        DR = D @ Rc[o.cam]  # d uv / d Xw
        RfX = np.einsum("nij,nj->ni", Rf[o.frame], o.point)
        Jf = np.empty((N, 2, FRAME_PARAMS))
        Jf[:, :, FRAME_RVEC] = np.cross(RfX[:, None, :], DR)
        Jf[:, :, FRAME_TVEC] = DR
        return Jc, Jf


def _tie_focal(Jc: np.ndarray, cam: np.ndarray, tie: np.ndarray | None) -> np.ndarray:
    """Camera Jacobian (N, 2, 15) with fy = fx for the cameras in ``tie`` (C,).

    The fx column moves both focal lengths (the fy column is then fixed).
    """
    if tie is not None and tie.any():
        Jc[:, :, 0] += tie[cam][:, None] * Jc[:, :, 1]
    return Jc


@dataclass(frozen=True)
class NormalEquations:
    """Weighted Gauss-Newton blocks; fixed camera parameters get identity rows, zero gradient.

    Attributes:
        Hcc: (C, 15, 15) camera blocks.
        Hff: (F, 6, 6) board-pose blocks.
        Hcf: (C, F, 15, 6) camera × board-pose blocks.
        gc: (C, 15) camera gradient.
        gf: (F, 6) board-pose gradient.
    """

    Hcc: np.ndarray
    Hff: np.ndarray
    Hcf: np.ndarray
    gc: np.ndarray
    gf: np.ndarray


def normal_equations(
    prob: Problem,
    Rc: np.ndarray,
    Rf: np.ndarray,
    pr: Projection,
    r: np.ndarray,
    w: np.ndarray,
    free: np.ndarray,
    tie: np.ndarray | None = None,
) -> NormalEquations:
    """The weighted Gauss-Newton normal equations ``J^T W J``, ``J^T W r`` in blocks.

    Args:
        prob: the problem.
        Rc: (C, 3, 3) world→camera rotations.
        Rf: (F, 3, 3) board→world rotations.
        pr: the projection of :meth:`Problem.residuals`.
        r: (N, 2) residuals.
        w: (N,) non-negative weights.
        free: (C, 15) bool, the optimised camera parameters.
        tie: (C,) bool, cameras whose fy is tied to fx, or None.

    Returns:
        The blocks.
    """
    C, F = prob.C, prob.F
    nc, nf = CAM_PARAMS, FRAME_PARAMS
    pc, pf = prob.pair_cam, prob.pair_frame
    Jc, Jf = prob.jacobians(Rc, Rf, pr)
    Jc = _tie_focal(Jc, prob.obs.cam, tie)
    Jc = Jc * free.astype(float)[prob.obs.cam][:, None, :]
    sw = np.sqrt(w)  # robust weights are >= 0
    n_pairs, S = prob.n_pairs, prob.slots
    # sqrt(w) [J r], padded per (camera, frame) pair: (pairs, 2 slots, 15 + 6 + 1)
    M = np.zeros((n_pairs * S, 2, nc + nf + 1))
    M[prob.flat_slot] = np.concatenate([Jc, Jf, r[:, :, None]], axis=2) * sw[:, None, None]
    M = M.reshape(n_pairs, 2 * S, nc + nf + 1)
    G = M[:, :, : nc + nf].transpose(0, 2, 1) @ M  # (pairs, 21, 22): [Jc Jf]^T [Jc Jf r]
    Hcc = prob.cam_sum(G[:, :nc, :nc])
    gc = prob.cam_sum(G[:, :nc, nc + nf])
    Gf = G[prob.by_frame, nc:]
    Hff = prob.frame_sum(Gf[:, :, nc : nc + nf])
    gf = prob.frame_sum(Gf[:, :, nc + nf])
    Hcf = np.zeros((C, F, nc, nf))
    Hcf[pc, pf] = G[:, :nc, nc : nc + nf]
    fixed = ~free
    for c in range(C):
        idx = np.flatnonzero(fixed[c])
        Hcc[c, idx, :] = 0
        Hcc[c, :, idx] = 0
        Hcc[c, idx, idx] = 1.0
    gc[fixed] = 0.0
    return NormalEquations(Hcc, Hff, Hcf, gc, gf)


@dataclass(frozen=True)
class ReducedSystem:
    """The reduced camera system ``S dcam = rhs`` with the board poses eliminated.

    Attributes:
        S: (C*15, C*15) Schur complement.
        rhs: (C*15,) right-hand side.
        Hff_inv: (F, 6, 6) inverses of the board-pose blocks.
    """

    S: np.ndarray
    rhs: np.ndarray
    Hff_inv: np.ndarray


def schur(
    Hcc: np.ndarray, Hff: np.ndarray, Hcf: np.ndarray, gc: np.ndarray, gf: np.ndarray
) -> ReducedSystem:
    """Eliminate the board poses from the normal equations (Schur complement).

    Args:
        Hcc: (C, 15, 15) camera blocks.
        Hff: (F, 6, 6) board-pose blocks (invertible).
        Hcf: (C, F, 15, 6) camera × board-pose blocks.
        gc: (C, 15) camera gradient.
        gf: (F, 6) board-pose gradient.

    Returns:
        The reduced camera system.
    """
    C, F = Hcf.shape[:2]
    nc, nf = CAM_PARAMS, FRAME_PARAMS
    P = C * nc
    Hff_inv = np.linalg.inv(Hff)
    Hcf_flat = Hcf.transpose(0, 2, 1, 3).reshape(P, F * nf)
    Y = Hcf @ Hff_inv
    Y_flat = Y.transpose(0, 2, 1, 3).reshape(P, F * nf)
    S = np.zeros((P, P))
    for c in range(C):
        S[c * nc : (c + 1) * nc, c * nc : (c + 1) * nc] = Hcc[c]
    S -= Y_flat @ Hcf_flat.T
    rhs = -gc.reshape(P) + Y_flat @ gf.reshape(F * nf)
    return ReducedSystem(S, rhs, Hff_inv)
