"""Temporal smoothing of predicted poses with a posterior standard deviation per point.

Every keypoint follows a constant-velocity model on each world axis (state: position and
velocity, white-noise acceleration of spectral density ``q`` in mm^2/s^3). A frame's
measurement is the predicted position with variance ``sigma0^2 * c^-beta`` (``c`` the
frame's confidence, floored at :data:`MIN_CONFIDENCE`), so low-confidence frames count
little; frames without a prediction have no measurement and are filled by the smoother.
A measurement whose innovation is improbable under the filter (Mahalanobis distance over
the three axes above the 99.9 % point of chi-square with 3 degrees of freedom) is
rejected as an outlier; after :data:`MAX_REJECT_RUN` rejections in a row the keypoint is
taken as lost and the filter restarts from the next measurement. Where many more
predictions of a keypoint are rejected than the gate would reject under the model
(:func:`misfit_warning`), the model does not describe that keypoint's motion: the smoother
logs a warning and writes it into the provenance. A Rauch-Tung-Striebel
pass gives the posterior mean and variance of every frame; being a forward-backward
smoother it adds no lag.

One process noise per keypoint over a whole recording would damp a brief fast movement
(a stimulated paw's 5 Hz oscillation) or reject it as outliers, so the process noise is
raised per frame and axis where the measurements' second differences show a sustained
movement faster than the fitted model allows (:func:`adaptive_q_scale`).

The parameters ``(q, sigma0, beta)`` of each keypoint are fitted on the recording itself by
maximising the innovation likelihood of the Kalman filter in a pattern search (on at most
:data:`FIT_FRAMES` frames from the middle of the recording), so the reported uncertainty
follows the recording's own noise.

The filter is written here in NumPy rather than taken from a library: ``filterpy``
(``KalmanFilter.batch_filter`` / ``rts_smoother``) and ``pykalman`` run one series at a
time with per-step matrix calls in Python, which is too slow for a grid fit over
``K * 3`` series and dozens of parameter candidates, and neither fits the scale of a
per-frame measurement variance (pykalman's EM estimates one constant observation
covariance; filterpy fits nothing); ``simdkalman`` vectorises over series but its
``KalmanFilter`` takes one observation and one process noise per series (a per-frame
variance, process noise or outlier gate needs its ``primitives`` in a Python loop over
frames, which is what this module does); ``ensemble-kalman-smoother`` needs an ensemble
of networks and JAX. The scalar two-state filter below runs all series and all parameter
candidates at once as arrays.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from freipose.errors import FreiPoseError
from freipose.io.atomic import refuse_existing
from freipose.io.lock import output_lock
from freipose.io.poses import PoseData, read_poses_h5, write_poses_h5
from freipose.predict.smooth_error import HeldOutError

MIN_CONFIDENCE = 0.02
GATE_CHI2_3 = 16.27  # 99.9 % point of chi-square with 3 degrees of freedom
FIT_FRAMES = 4000
_P0 = 1e8  # prior variance of the first position (mm^2) and velocity ((mm/s)^2)

_ROUNDS = 12
CHI2_1_MEDIAN = 0.4549  # median of chi-square with 1 degree of freedom
ADAPT_WINDOW = 9
ADAPT_THRESHOLD = 4.0
MAX_Q_SCALE = 1e5
MAX_REJECT_RUN = 3
MISFIT_REJECTED = 0.02

log = logging.getLogger(__name__)


class SmoothingError(FreiPoseError):
    """The poses cannot be smoothed (too few predicted frames of a keypoint)."""


@dataclass(frozen=True)
class SmootherParams:
    """Fitted parameters of the smoother, one value per keypoint.

    Attributes:
        q: (K,) process noise, white-noise acceleration spectral density in mm^2/s^3.
        sigma0: (K,) measurement standard deviation in mm at confidence 1.
        beta: (K,) exponent of the confidence: variance = sigma0^2 * c^-beta.
    """

    q: np.ndarray
    sigma0: np.ndarray
    beta: np.ndarray

    def as_dict(self, keypoints: tuple[str, ...]) -> dict[str, Any]:
        """The parameters per keypoint name, for provenance."""
        return {
            name: {"q_mm2_s3": float(q), "sigma0_mm": float(s), "beta": float(b)}
            for name, q, s, b in zip(keypoints, self.q, self.sigma0, self.beta, strict=True)
        }


@dataclass(frozen=True)
class SmoothResult:
    """Posterior of the smoother.

    Attributes:
        mean: (T, K, 3) posterior mean in mm.
        std: (T, K, 3) posterior standard deviation in mm, per axis.
        filled: (T, K) frames without a prediction (filled by the smoother).
        rejected: (T, K) predictions rejected as outliers.
        params: the fitted parameters.
        loglik: (K,) innovation log-likelihood of the fitted parameters on the fit frames.
        q_scale: (T, K, 3) factor on the process noise per frame and axis
            (:func:`adaptive_q_scale`; all 1 without adaptation).
    """

    mean: np.ndarray
    std: np.ndarray
    filled: np.ndarray
    rejected: np.ndarray
    params: SmootherParams
    loglik: np.ndarray
    q_scale: np.ndarray

    @property
    def q_raised(self) -> int:
        """The number of frames and keypoints whose process noise was raised on some axis."""
        return int((self.q_scale > 1.0).any(axis=-1).sum())


@dataclass(frozen=True)
class _Pass:
    """Forward-filter output: log-likelihood, rejections and the per-frame states (if kept)."""

    loglik: np.ndarray
    rejected: np.ndarray
    states: tuple[np.ndarray, ...]


def _meas_var(conf: np.ndarray, sigma0: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """(G, K, 1) parameters and (K,) confidences -> (G, K, 1) measurement variances.

    ``conf`` may be divided by a reference confidence (as in :func:`fit_params`); the
    floor :data:`MIN_CONFIDENCE` is applied by the caller.
    """
    return sigma0**2 * conf[None, :, None] ** (-beta)


def _forward(
    z: np.ndarray,
    conf: np.ndarray,
    dt: np.ndarray,
    params: tuple[np.ndarray, np.ndarray, np.ndarray],
    keep: bool,
    q_scale: np.ndarray | None = None,
) -> _Pass:
    """Kalman filter of every series and parameter candidate at once.

    Args:
        z: (T, K, 3) measurements in mm, NaN where missing.
        conf: (T, K) confidences.
        dt: (T,) seconds from the previous frame (dt[0] unused).
        params: q, sigma0, beta, each (G, K, 1).
        keep: keep the filtered and predicted states for the smoother.
        q_scale: (T, K, 3) factor on ``q`` in the step into each frame (None: 1).
    """
    q_fit, sigma0, beta = params
    q = q_fit
    t_n, k_n, _ = z.shape
    shape = np.broadcast_shapes(q.shape, (1, k_n, 3))
    valid = np.isfinite(z).all(axis=-1)
    first = np.where(valid.any(axis=0), valid.argmax(axis=0), 0)
    x = np.broadcast_to(np.nan_to_num(z[first, np.arange(k_n)])[None], shape).copy()
    v = np.zeros(shape)
    p00, p01, p11 = np.full(shape, _P0), np.zeros(shape), np.full(shape, _P0)
    loglik = np.zeros(shape[:2])
    streak = np.zeros(shape[:2], np.int64)
    rejected = np.zeros((t_n, k_n), bool) if q.shape[0] == 1 else None
    out = [np.empty((t_n, *shape)) for _ in range(10)] if keep else None
    for t in range(t_n):
        if t > 0:
            h = dt[t]
            if q_scale is not None:
                q = q_fit * q_scale[t][None]
            x = x + h * v
            p00 = p00 + 2 * h * p01 + h * h * p11 + q * h**3 / 3
            p01 = p01 + h * p11 + q * h * h / 2
            p11 = p11 + q * h
        if out is not None:
            for arr, val in zip(out[5:], (x, v, p00, p01, p11), strict=True):
                arr[t] = val
        ok = valid[t]
        if ok.any():
            r = _meas_var(conf[t], sigma0, beta)
            s = p00 + r
            e = np.where(ok[None, :, None], np.nan_to_num(z[t])[None] - x, 0.0)
            d2 = (e * e / s).sum(axis=-1)
            use = ok[None] & (d2 <= GATE_CHI2_3)
            ll = -0.5 * (np.log(2 * np.pi * s).sum(axis=-1) + np.minimum(d2, GATE_CHI2_3))
            # the first measurement of a series has the diffuse prior: it adds no evidence
            counts = ok[None] & (t > first)[None]
            loglik += np.where(counts, ll, 0.0)
            # after MAX_REJECT_RUN rejections in a row the filter has lost the keypoint:
            # it restarts from this measurement with the diffuse prior
            restart = ok[None] & ~use & (streak >= MAX_REJECT_RUN)
            streak = np.where(ok[None], np.where(use | restart, 0, streak + 1), streak)
            if restart.any():
                rs = restart[..., None]
                v = np.where(rs, 0.0, v)
                p00, p01, p11 = (
                    np.where(rs, _P0, p00),
                    np.where(rs, 0.0, p01),
                    np.where(rs, _P0, p11),
                )
                s = np.where(rs, p00 + r, s)
                use = use | restart
            if rejected is not None:
                rejected[t] = ok & ~use[0]
            u = use[..., None]
            k0, k1 = np.where(u, p00 / s, 0.0), np.where(u, p01 / s, 0.0)
            x, v = x + k0 * e, v + k1 * e
            p00, p01, p11 = p00 - k0 * p00, p01 - k0 * p01, p11 - k1 * p01
        if out is not None:
            for arr, val in zip(out[:5], (x, v, p00, p01, p11), strict=True):
                arr[t] = val
    return _Pass(loglik, rejected if rejected is not None else np.zeros(0), tuple(out or ()))


def _rts(states: tuple[np.ndarray, ...], dt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rauch-Tung-Striebel pass: filtered and predicted states -> position mean, variance."""
    fx, fv, f00, f01, f11, px, pv, p00, p01, p11 = states
    t_n = fx.shape[0]
    mx, mv, m00, m01, m11 = fx[-1].copy(), fv[-1].copy(), f00[-1].copy(), f01[-1].copy(), f11[-1]
    mean, var = np.empty_like(fx), np.empty_like(fx)
    mean[-1], var[-1] = mx, m00
    for t in range(t_n - 2, -1, -1):
        h = dt[t + 1]
        # C = P_f F^T P_p^-1 with F = [[1, h], [0, 1]]
        a00, a01 = f00[t] + h * f01[t], f01[t]
        a10, a11 = f01[t] + h * f11[t], f11[t]
        det = p00[t + 1] * p11[t + 1] - p01[t + 1] ** 2
        i00, i01, i11 = p11[t + 1] / det, -p01[t + 1] / det, p00[t + 1] / det
        c00, c01 = a00 * i00 + a01 * i01, a00 * i01 + a01 * i11
        c10, c11 = a10 * i00 + a11 * i01, a10 * i01 + a11 * i11
        dx, dv = mx - px[t + 1], mv - pv[t + 1]
        d00, d01, d11 = m00 - p00[t + 1], m01 - p01[t + 1], m11 - p11[t + 1]
        mx = fx[t] + c00 * dx + c01 * dv
        mv = fv[t] + c10 * dx + c11 * dv
        # P_s = P_f + C (M - P_p) C^T
        n00 = f00[t] + c00 * (c00 * d00 + c01 * d01) + c01 * (c00 * d01 + c01 * d11)
        n01 = f01[t] + c00 * (c10 * d00 + c11 * d01) + c01 * (c10 * d01 + c11 * d11)
        n11 = f11[t] + c10 * (c10 * d00 + c11 * d01) + c11 * (c10 * d01 + c11 * d11)
        m00, m01, m11 = n00, n01, n11
        mean[t], var[t] = mx, m00
    return mean, var


def _candidates(center: np.ndarray, step: np.ndarray) -> tuple[np.ndarray, ...]:
    """The 27 neighbours of a (3, K) centre (log q, log sigma0, beta) -> three (27, K, 1)."""
    f = np.stack(np.meshgrid(*([np.array([-1.0, 0.0, 1.0])] * 3), indexing="ij")).reshape(3, -1)
    pts = center[:, None, :] + f[:, :, None] * step[:, None, :]  # (3, 27, K)
    return np.exp(pts[0])[..., None], np.exp(pts[1])[..., None], np.maximum(pts[2], 0.0)[..., None]


def fit_params(
    z: np.ndarray, conf: np.ndarray, dt: np.ndarray
) -> tuple[SmootherParams, np.ndarray]:
    """Maximum-likelihood smoother parameters per keypoint, by a pattern search.

    The search starts at ``q = 1e5 mm^2/s^3, sigma0 = 3 mm, beta = 1`` with steps of a factor
    10 in ``q``, 3.16 in ``sigma0`` and 0.5 in ``beta``; every round evaluates the 27
    neighbours of each keypoint's centre, moves to the best one, and halves the steps where
    the centre was best.

    Args:
        z: (T, K, 3) measurements in mm, NaN where missing.
        conf: (T, K) confidences in [0, 1].
        dt: (T,) seconds from the previous frame.

    Returns:
        The parameters and the (K,) log-likelihood they reach.
    """
    t_n, k_n, _ = z.shape
    lo = max(0, (t_n - FIT_FRAMES) // 2)
    z, conf, dt = z[lo : lo + FIT_FRAMES], conf[lo : lo + FIT_FRAMES], dt[lo : lo + FIT_FRAMES]
    # searched as sigma at the median confidence, so that sigma and beta hardly correlate
    c = np.clip(conf, MIN_CONFIDENCE, 1.0)
    ref = np.array([np.median(c[np.isfinite(z[:, j, 0]), j]) for j in range(k_n)])
    c = c / ref
    center = np.array([np.log(1e5), np.log(3.0), 1.0])[:, None] * np.ones((1, k_n))
    step = np.array([np.log(10.0), np.log(10.0) / 2, 0.5])[:, None] * np.ones((1, k_n))
    k = np.arange(k_n)
    ll_best = np.full(k_n, -np.inf)
    for _ in range(_ROUNDS):
        q, s, b = _candidates(center, step)
        ll = _forward(z, c, dt, (q, s, b), keep=False).loglik
        i = ll.argmax(axis=0)
        ll_best = ll[i, k]
        stay = ll_best <= ll[13, k]  # 13: the centre of the 3 x 3 x 3 neighbours
        center = np.stack([np.log(q[i, k, 0]), np.log(s[i, k, 0]), b[i, k, 0]])
        step = np.where(stay[None], step / 2, step)
    sigma0 = np.exp(center[1]) * ref ** (center[2] / 2)
    return SmootherParams(np.exp(center[0]), sigma0, center[2]), ll_best


def adaptive_q_scale(
    z: np.ndarray, conf: np.ndarray, dt: np.ndarray, params: SmootherParams
) -> np.ndarray:
    """(T, K, 3) factor on the fitted process noise where the poses move faster than it allows.

    Under the model, the second difference ``a = z[t+1] - 2 z[t] + z[t-1]`` of an axis has
    variance ``E = r[t-1] + 4 r[t] + r[t+1] + 2/3 q h^3`` (``r`` the measurement variances).
    The running median of ``a^2 / E`` over :data:`ADAPT_WINDOW` frames, over its median
    under the model (:data:`CHI2_1_MEDIAN`), estimates by how much the local motion exceeds
    the model. Where the window's lower quartile of that ratio reaches
    :data:`ADAPT_THRESHOLD` (three quarters of the window move too fast: a sustained
    movement, not a few outliers, which only touch the three second differences around
    each), the process noise of that frame and axis is raised so that the model's ``E``
    matches the median, and the smoother follows a brief fast movement (a stimulated
    paw's oscillation) instead of damping it or rejecting it as outliers. The estimate
    comes from the measurements alone (no filter feedback). Frames without enough second
    differences keep factor 1.

    Args:
        z: (T, K, 3) measurements in mm, NaN where missing.
        conf: (T, K) confidences, floored at :data:`MIN_CONFIDENCE`.
        dt: (T,) seconds from the previous frame.
        params: the fitted parameters.
    """
    r = _meas_var_frames(conf, params)  # (T, K)
    h = np.concatenate([dt[1:], dt[-1:]])[:, None, None]
    q = params.q[None, :, None]
    a2 = np.full(z.shape, np.nan)
    a2[1:-1] = (z[2:] - 2 * z[1:-1] + z[:-2]) ** 2
    vr = np.full(r.shape, np.nan)
    vr[1:-1] = r[:-2] + 4 * r[1:-1] + r[2:]
    e = vr[..., None] + 2 / 3 * q * h**3
    pad = ADAPT_WINDOW // 2
    ratio = np.pad(a2 / e / CHI2_1_MEDIAN, ((pad, pad), (0, 0), (0, 0)), constant_values=np.nan)
    win = np.lib.stride_tricks.sliding_window_view(ratio, ADAPT_WINDOW, axis=0)
    enough = np.isfinite(win).sum(axis=-1) > pad
    lo, m = np.nanquantile(np.where(enough[..., None], win, 0.0), [0.25, 0.5], axis=-1)
    q_new = (np.where(enough, m, 1.0) * e - vr[..., None]) * 1.5 / h**3
    scale = np.where(enough & (lo >= ADAPT_THRESHOLD), q_new / q, 1.0)
    return np.clip(np.nan_to_num(scale, nan=1.0), 1.0, MAX_Q_SCALE)


def _meas_var_frames(conf: np.ndarray, params: SmootherParams) -> np.ndarray:
    """(T, K) measurement variances (mm^2) of the frames, from the floored confidences."""
    return params.sigma0[None] ** 2 * conf ** (-params.beta[None])


def smooth_arrays(
    z: np.ndarray,
    conf: np.ndarray,
    dt: np.ndarray,
    params: SmootherParams | None = None,
    adaptive: bool = True,
) -> SmoothResult:
    """Smooth (T, K, 3) positions with their (T, K) confidences.

    Args:
        z: (T, K, 3) positions in mm, NaN where there is no prediction.
        conf: (T, K) confidences in [0, 1] (NaN counts as missing).
        dt: (T,) seconds from the previous frame (dt[0] unused), all positive.
        params: fixed parameters; fitted on the data when None.
        adaptive: raise the process noise per frame and axis where the poses move faster
            than the fitted one allows (:func:`adaptive_q_scale`), so that brief fast
            movements are followed rather than damped or rejected as outliers.

    Returns:
        The posterior mean and standard deviation per frame, keypoint and axis.

    Raises:
        SmoothingError: a keypoint has fewer than 3 predicted frames.
    """
    z = np.asarray(z, np.float64)
    conf = np.clip(np.nan_to_num(np.asarray(conf, np.float64), nan=0.0), MIN_CONFIDENCE, 1.0)
    valid = np.isfinite(z).all(axis=-1)
    z = np.where(valid[..., None], z, np.nan)
    few = np.flatnonzero(valid.sum(axis=0) < 3)
    if few.size:
        raise SmoothingError(
            f"keypoints {few.tolist()} have fewer than 3 predicted frames of {z.shape[0]}; "
            "a smoother needs at least 3 (predict a longer part of the recording)"
        )
    loglik = np.zeros(z.shape[1])
    if params is None:
        params, loglik = fit_params(z, conf, dt)
    p = (params.q[None, :, None], params.sigma0[None, :, None], params.beta[None, :, None])
    scale = adaptive_q_scale(z, conf, dt, params) if adaptive else np.ones(z.shape)
    run = _forward(z, conf, dt, p, keep=True, q_scale=scale if adaptive else None)
    mean, var = _rts(run.states, dt)
    return SmoothResult(
        mean=mean[:, 0],
        std=np.sqrt(np.maximum(var[:, 0], 0.0)),
        filled=~valid,
        rejected=run.rejected,
        params=params,
        loglik=loglik,
        q_scale=scale,
    )


def misfit_warning(res: SmoothResult, keypoints: tuple[str, ...]) -> str | None:
    """The keypoints with more than :data:`MISFIT_REJECTED` of their predictions rejected.

    The gate rejects about 0.1 % of what fits the fitted model; far more means that the
    model does not describe the keypoint's motion, and the smoothed track may have damped
    or dropped fast real movements. Returns the warning, or None.
    """
    frac = res.rejected.sum(axis=0) / np.maximum((~res.filled).sum(axis=0), 1)
    bad = [f"{k} {100 * f:.0f} %" for k, f in zip(keypoints, frac, strict=True)]
    bad = [b for b, f in zip(bad, frac, strict=True) if f > MISFIT_REJECTED]
    return None if not bad else (
        f"the smoother rejected more than {100 * MISFIT_REJECTED:.0f} % of the predictions of "
        f"{len(bad)} keypoints as outliers ({', '.join(bad)}; its noise model rejects about "
        "0.1 %): the model fitted on the recording does not describe their motion, and the "
        "smoothed track may have damped or dropped fast real movements; compare it with the "
        "raw poses before analysing it"
    )  # fmt: skip


def frame_intervals(frame_index: np.ndarray, fps: float) -> np.ndarray:
    """(T,) seconds between consecutive frames (the first is 1 / fps)."""
    steps = np.diff(np.asarray(frame_index, np.int64), prepend=frame_index[0] - 1)
    if (steps <= 0).any():
        raise SmoothingError("frame_index must increase; the poses file has repeated frames")
    return steps / float(fps)


def _persistent(
    error_floor: np.ndarray | HeldOutError | None, keypoints: tuple[str, ...]
) -> tuple[np.ndarray, dict[str, Any] | None]:
    """(K, 3) persistent error in mm (0 without one) and its provenance entry."""
    if isinstance(error_floor, HeldOutError):
        floor = error_floor.for_keypoints(keypoints)
        return floor, {"kind": "error on held-out labels", **error_floor.as_dict()}
    if error_floor is None:
        return np.zeros((len(keypoints), 3)), None
    floor = np.asarray(error_floor, np.float64).reshape(len(keypoints), -1)
    floor = np.broadcast_to(floor, (len(keypoints), 3))
    entry = {k: [float(v) for v in f] for k, f in zip(keypoints, floor, strict=True)}
    return floor, {"kind": "floor", "floor_mm": entry}


def _bones(data: PoseData, mean: np.ndarray, var: np.ndarray) -> tuple[np.ndarray, dict]:
    """Bone-constrained positions and the provenance entry (lengths and spreads).

    Raises:
        SmoothingError: the poses' skeleton has no limb between two single keypoints.
    """
    from freipose.predict.smooth_bones import bone_pairs, constrain_bones

    pairs = bone_pairs(data.skeleton, data.keypoints)
    if not len(pairs):
        raise SmoothingError(
            "--bones needs a skeleton with limbs between single keypoints; the poses file "
            f"has {'no skeleton' if data.skeleton is None else 'none'} (leave out --bones)"
        )
    fit = constrain_bones(mean, var, pairs)
    names = [f"{data.keypoints[i]} - {data.keypoints[j]}" for i, j in pairs]
    entry = {
        n: {"length_mm": float(ln), "spread_mm": float(sp)}
        for n, ln, sp in zip(names, fit.length, fit.spread, strict=True)
    }
    return fit.mean, entry


def smooth_poses(
    data: PoseData,
    source: str = "",
    error_floor: np.ndarray | HeldOutError | None = None,
    bones: bool = False,
) -> PoseData:
    """The smoothed poses of one recording, same schema plus the posterior.

    ``extra/smooth_std`` (T, K, 3) holds the posterior standard deviation in mm per axis,
    ``extra/filled`` (T, K) the frames without a prediction, ``extra/rejected`` (T, K) the
    predictions rejected as outliers; the confidences stay the network's. The provenance
    gains ``smoother`` with the method and the fitted parameters per keypoint.

    Args:
        data: the predicted poses.
        source: the poses file, for provenance.
        error_floor: the persistent error added in quadrature to the standard deviation:
            the network's error on held-out labels (:class:`HeldOutError`, from
            :func:`freipose.predict.smooth_error.model_validation_error`), or a (K,) or
            (K, 3) floor in mm (:func:`freipose.predict.smooth_error.fit_error_floor`).
        bones: pull the skeleton's bone lengths towards their median over the recording
            (:mod:`freipose.predict.smooth_bones`); the standard deviation stays the
            smoother's.

    Raises:
        SmoothingError: too few predicted frames, or ``bones`` without usable limbs.
    """
    res = smooth_arrays(data.poses, data.confidence, frame_intervals(data.frame_index, data.fps))
    floor, persistent = _persistent(error_floor, data.keypoints)
    std = np.sqrt(res.std**2 + floor[None] ** 2)
    mean, bone_entry = res.mean, None
    if bones:
        mean, bone_entry = _bones(data, res.mean, res.std**2)
    prov: dict[str, Any] = dict(data.provenance)
    prov["smoother"] = {
        "method": "constant-velocity Kalman filter + RTS smoother (freipose.predict.smooth)",
        "measurement_variance": "sigma0^2 * max(confidence, 0.02)^-beta",
        "outlier_gate_chi2_3dof": GATE_CHI2_3,
        "adaptive_process_noise": {
            "window_frames": ADAPT_WINDOW,
            "threshold": ADAPT_THRESHOLD,
            "frames_raised": int(res.q_raised),
        },
        "fitted_by": "maximum innovation likelihood on the recording",
        "params": res.params.as_dict(data.keypoints),
        "source": source,
    }
    warning = misfit_warning(res, data.keypoints)
    if warning is not None:
        log.warning("%s: %s", source or "poses", warning)
        prov["smoother"]["warning"] = warning
    if persistent is not None:
        prov["smoother"]["persistent_error"] = persistent
    if bone_entry is not None:
        prov["smoother"]["bones"] = bone_entry
    extra: Mapping[str, np.ndarray] = {
        **dict(data.extra),
        "smooth_std": std.astype(np.float32),
        "filled": res.filled,
        "rejected": res.rejected,
    }
    return dataclasses.replace(data, poses=mean.astype(np.float32), provenance=prov, extra=extra)


def refuse_same(src: Path, dst: Path) -> None:
    """Refuse an output that is its own input.

    Raises:
        SmoothingError: ``dst`` is the file ``src``.
    """
    if dst.resolve() == src.resolve():
        raise SmoothingError(
            f"the smoothed poses would replace their input {src}; pass another -o folder"
        )


def smooth_file(
    src: str | Path,
    dst: str | Path,
    overwrite: bool = False,
    error_floor: HeldOutError | None = None,
    bones: bool = False,
) -> Path:
    """Smooth the poses file ``src`` into ``dst`` (atomically, under the output lock).

    ``error_floor`` and ``bones`` are those of :func:`smooth_poses`.

    Raises:
        SmoothingError: ``dst`` is ``src``, or the poses cannot be smoothed.
        OutputExistsError: ``dst`` exists and ``overwrite`` is false.
        PosesFormatError: ``src`` is not a readable poses file.
    """
    src, dst = Path(src), Path(dst)
    refuse_same(src, dst)
    refuse_existing(dst, overwrite)
    with output_lock(dst, "smoothed poses file"):
        refuse_existing(dst, overwrite)
        data = read_poses_h5(src)
        out = smooth_poses(data, source=str(src), error_floor=error_floor, bones=bones)
        write_poses_h5(out, dst)
    return dst
