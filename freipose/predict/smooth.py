"""Temporal smoothing of predicted poses with a posterior standard deviation per point.

The model (:mod:`freipose.predict.smooth_filter`): every keypoint's true position follows
a constant-velocity model on each world axis, and the network's prediction is the true
position plus a correlated error (an offset that drifts with a correlation time of its
own, as a network's error persists over several frames) plus a white error with
Student-t tails, one scale per keypoint: the network's confidence falls where a body
part takes an unusual pose (a stimulated paw lifted and oscillating), and a variance
that grew as it fell would damp exactly those movements (on the demo's predictions the
paw's 5 Hz amplitude fell from 6.6 mm raw to 5.6 mm smoothed); a far-off prediction
counts little through its Student-t weight instead. Its parameters are
fitted per keypoint on the recording itself (maximum likelihood, on at most
:data:`~freipose.predict.smooth_filter.FIT_FRAMES` frames from the middle), so the
smoother follows the recording's own noise; a Rauch-Tung-Striebel pass gives the
posterior mean and covariance of every frame without lag. The position reported is the
smoothed track (position plus correlated error): one recording cannot tell the
correlated error from movement reliably, and subtracting its estimate moves the track
off the truth; the standard deviation covers the difference.

Heavy tails instead of a gate: after a first pass weighted on line, every measurement
is weighted by ``(NU + 3) / (NU + d2)`` from its residual against the smoothed track
(:data:`IRLS_PASSES` iteratively reweighted passes, as for a Student-t error), so a
measurement that deviates within the correlated error keeps nearly its full weight, and
only gross outliers are left out (``rejected``): spikes that leave their neighbours'
level and return, far beyond the keypoint's typical residual (:func:`_residual_weights`).
A large residual that is no spike is a sudden step: the process noise of its frame is
raised and the next pass follows it (:func:`_lagging_scale`). After
:data:`~freipose.predict.smooth_filter.MAX_REJECT_RUN` gross outliers in a row the
keypoint is taken as lost and the filter restarts from the next measurement; where many
more predictions of a keypoint are gross outliers than the model expects
(:func:`misfit_warning`), the smoother warns and writes it into the provenance.

One process noise per keypoint over a whole recording would damp a brief fast movement
(a stimulated paw's 5 Hz oscillation) or take it for the network's error, so the process
noise is raised per frame and axis where the measurements' second differences show a
sustained movement faster than the fitted model allows (:func:`adaptive_q_scale`).

The filter is written here in NumPy rather than taken from a library: ``filterpy`` and
``pykalman`` run one series at a time with per-step matrix calls in Python, which is too
slow for fitting ``K * 3`` series over many parameter candidates, and neither fits a
per-frame measurement variance (pykalman's EM estimates one constant observation
covariance); ``simdkalman`` takes one observation and process noise per series;
``ensemble-kalman-smoother`` (Lightning Pose's EKS) takes its per-frame variance from
the spread of an ensemble of networks (several trained models, or augmented copies of
each frame) and a white measurement error, and needs JAX: one network's predictions give
it no ensemble, its white error would take the network's correlated error for movement
or damp movement as noise, and a per-frame variance from the network's own uncertainty
(its confidence, or the spread of the views' points about the 3D pose, which on the
demo's predictions tracks the error no better than the confidence: rank correlation
0.54-0.56 against 0.59) rises where the poses are unusual, not where they jitter. Nor
does an ensemble take the persistent error away: the predictions of augmented copies of
each frame (the voxel grid turned about the up, the cube shifted by up to a voxel) and
of networks fine-tuned with different seeds err nearly alike
(``benchmarks/smooth_ensembles.py``; ``docs/how-to/smooth.md`` gives the figures).
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
from freipose.io.animals import stack_animals
from freipose.io.atomic import refuse_existing
from freipose.io.lock import output_lock
from freipose.io.poses import PoseData, read_poses_h5, write_poses_h5
from freipose.predict.smooth_error import HeldOutError
from freipose.predict.smooth_filter import (
    GROSS_D2,
    MIN_CONFIDENCE,
    NU,
    SmootherParams,
    fit_params,
    forward,
    rts,
)

CHI2_1_MEDIAN = 0.4549  # median of chi-square with 1 degree of freedom
CHI2_3_MEDIAN = 2.366  # median of chi-square with 3 degrees of freedom
ADAPT_WINDOW = 9
ADAPT_THRESHOLD = 4.0
ADAPT_QUANTILE = 0.5
ADAPT_BOOST = 4.0
MAX_Q_SCALE = 1e5
IRLS_PASSES = 2
LAG_D2 = 16.0
MISFIT_REJECTED = 0.02

log = logging.getLogger(__name__)

__all__ = ["SmootherParams", "SmoothResult", "SmoothingError", "smooth_arrays", "smooth_poses"]


class SmoothingError(FreiPoseError):
    """The poses cannot be smoothed (too few predicted frames of a keypoint)."""


@dataclass(frozen=True)
class SmoothResult:
    """Posterior of the smoother.

    Attributes:
        mean: (T, K, 3) the smoothed track in mm: the posterior mean of position plus
            correlated error, i.e. the predictions without their white error and gross
            outliers (the correlated error cannot be told from movement reliably in one
            recording, and subtracting its estimate moves the track off the truth).
        std: (T, K, 3) standard deviation of the true position about ``mean`` in mm, per
            axis: the position's posterior variance plus the estimated correlated error
            squared (the mean squared error of ``mean`` under the model).
        track_std: (T, K, 3) posterior standard deviation of the predicted track (position
            plus correlated error) in mm: the white noise the smoother removes.
        offset: (T, K, 3) posterior mean of the correlated error in mm.
        filled: (T, K) frames without a prediction (filled by the smoother).
        rejected: (T, K) gross outliers left out.
        weight: (T, K) Student-t weight of every measurement (0 where missing or rejected).
        params: the fitted parameters.
        loglik: (K,) log-likelihood of the fitted parameters on the fit frames.
        q_scale: (T, K, 3) factor on the process noise per frame and axis
            (:func:`adaptive_q_scale`; all 1 without adaptation).
    """

    mean: np.ndarray
    std: np.ndarray
    track_std: np.ndarray
    offset: np.ndarray
    filled: np.ndarray
    rejected: np.ndarray
    weight: np.ndarray
    params: SmootherParams
    loglik: np.ndarray
    q_scale: np.ndarray

    @property
    def q_raised(self) -> int:
        """The number of frames and keypoints whose process noise was raised on some axis."""
        return int((self.q_scale > 1.0).any(axis=-1).sum())


def _meas_var_frames(conf: np.ndarray, params: SmootherParams) -> np.ndarray:
    """(T, K) white measurement variances (mm^2) of the frames, from floored confidences."""
    return params.sigma0[None] ** 2 * conf ** (-params.beta[None])


def adaptive_q_scale(
    z: np.ndarray, conf: np.ndarray, dt: np.ndarray, params: SmootherParams
) -> np.ndarray:
    """(T, K, 3) factor on the fitted process noise where the poses move faster than it allows.

    Under the model, the second difference ``a = z[t+1] - 2 z[t] + z[t-1]`` of an axis has
    variance ``E = r[t-1] + 4 r[t] + r[t+1] + 2 s^2 (1 - phi) (3 - phi) + 2/3 q h^3`` (``r``
    the white measurement variances, ``s`` and ``phi`` the correlated error's standard
    deviation and frame-to-frame correlation). The running median of ``a^2 / E`` over
    :data:`ADAPT_WINDOW` frames, over its median under the model (:data:`CHI2_1_MEDIAN`),
    estimates by how much the local motion exceeds the model. Where that median reaches
    :data:`ADAPT_THRESHOLD` (half of the window moves too fast: a sustained movement, not
    a spike, which changes three second differences; an oscillation's second differences
    pass near zero twice a period, so a lower quantile would miss it), the process noise of that
    frame and axis is raised to :data:`ADAPT_BOOST` times what makes the model's ``E``
    match the median, so that the movement, not the network's error, explains the fast
    change, and the smoother follows a brief fast movement (a stimulated paw's
    oscillation) instead of damping it. The estimate comes from the measurements alone;
    gross spikes (:func:`_gross_spikes`) are left out of it, so a few outliers in a row do
    not pass for movement.
    Frames without enough second differences keep factor 1.

    Args:
        z: (T, K, 3) measurements in mm, NaN where missing.
        conf: (T, K) confidences, floored at :data:`MIN_CONFIDENCE`.
        dt: (T,) seconds from the previous frame.
        params: the fitted parameters.
    """
    r = _meas_var_frames(conf, params) * NU / (NU - 2)  # (T, K) Student-t variances
    z = np.where(_gross_spikes(z)[..., None], np.nan, z)
    h = np.concatenate([dt[1:], dt[-1:]])[:, None, None]
    q = params.q[None, :, None]
    phi = np.exp(-h / params.offset_tau[None, :, None])
    vb = 2 * params.offset_sd[None, :, None] ** 2 * (1 - phi) * (3 - phi)
    a2 = np.full(z.shape, np.nan)
    a2[1:-1] = (z[2:] - 2 * z[1:-1] + z[:-2]) ** 2
    vr = np.full(r.shape, np.nan)
    vr[1:-1] = r[:-2] + 4 * r[1:-1] + r[2:]
    noise = vr[..., None] + vb
    e = noise + 2 / 3 * q * h**3
    pad = ADAPT_WINDOW // 2
    ratio = np.pad(a2 / e / CHI2_1_MEDIAN, ((pad, pad), (0, 0), (0, 0)), constant_values=np.nan)
    win = np.lib.stride_tricks.sliding_window_view(ratio, ADAPT_WINDOW, axis=0)
    enough = np.isfinite(win).sum(axis=-1) > pad
    lo, m = _row_quantiles(np.where(enough[..., None], win, 0.0), (ADAPT_QUANTILE, 0.5))
    q_new = ADAPT_BOOST * (np.where(enough, m, 1.0) * e - noise) * 1.5 / h**3
    scale = np.where(enough & (lo >= ADAPT_THRESHOLD), q_new / q, 1.0)
    scale = np.clip(np.nan_to_num(scale, nan=1.0), 1.0, MAX_Q_SCALE)
    # the whole window of a raised frame moves fast: its edges and dips are raised too
    wide = np.pad(scale, ((pad, pad), (0, 0), (0, 0)), constant_values=1.0)
    return np.lib.stride_tricks.sliding_window_view(wide, ADAPT_WINDOW, axis=0).max(axis=-1)


def _row_quantiles(x: np.ndarray, quantiles: tuple[float, ...]) -> list[np.ndarray]:
    """``np.nanquantile(x, q, axis=-1)`` for each ``q`` (its linear method), every row at once.

    The same floats as NumPy's, which treats a row with NaNs on its own (a Python loop
    over the rows); here the rows are sorted together and each quantile interpolated
    between its two neighbours among the row's values.

    Args:
        x: (..., N) values, NaN where there is none.
        quantiles: quantiles in [0, 1].

    Returns:
        One (...) array per quantile, NaN for a row without values.
    """
    xs = np.sort(x, axis=-1)  # NaN last
    n = (~np.isnan(x)).sum(axis=-1)[..., None]
    out = []
    for q in quantiles:
        v = (n - 1) * np.float64(q)
        top = v >= n - 1  # NumPy's index -1: the largest value, its weight counted from -1
        prev = np.where(top, -1.0, np.floor(v))
        gamma = v - prev
        lo = np.take_along_axis(xs, np.where(top, n - 1, prev).astype(np.intp).clip(0), -1)
        hi = np.take_along_axis(xs, np.where(top, n - 1, prev + 1).astype(np.intp).clip(0), -1)
        diff = hi - lo
        res = np.where(gamma >= 0.5, hi - diff * (1 - gamma), lo + diff * gamma)
        out.append(np.where(n > 0, res, np.nan)[..., 0])
    return out


def _spikes(z: np.ndarray) -> np.ndarray:
    """(T, K) predictions that leave their neighbours' level and return: a spike, not a step.

    The deviation from the neighbours' mean is more than twice the neighbours' own
    difference; without both neighbours a prediction counts as a spike.
    """
    pad = np.pad(z, ((1, 1), (0, 0), (0, 0)), constant_values=np.nan)
    dev = np.linalg.norm(pad[1:-1] - (pad[:-2] + pad[2:]) / 2, axis=-1)
    gap = np.linalg.norm(pad[2:] - pad[:-2], axis=-1)
    return np.where(np.isfinite(gap), dev > 2 * gap, True)


def _gross_spikes(z: np.ndarray) -> np.ndarray:
    """(T, K) spikes (:func:`_spikes`) far beyond the keypoint's typical frame-to-frame change.

    A spike's squared second difference (over the three axes) exceeds :data:`GROSS_D2` times
    the keypoint's robust one (its median over the recording, over the median of a
    chi-square with 3 degrees of freedom), so an oscillation's turning points stay.
    """
    a2 = np.full(z.shape[:2], np.nan)
    a2[1:-1] = ((z[2:] - 2 * z[1:-1] + z[:-2]) ** 2).sum(axis=-1)
    typical = np.nanmedian(a2, axis=0, keepdims=True) / CHI2_3_MEDIAN
    with np.errstate(invalid="ignore"):
        return _spikes(z) & (a2 > GROSS_D2 * typical)


def _residual_scale(z: np.ndarray, r: np.ndarray, e2: np.ndarray) -> np.ndarray:
    """(T, K) scale of a squared residual.

    The largest of the white variance, the keypoint's robust residual variance and its
    robust frame-to-frame change (median squared second difference).
    """
    typical = np.nanmedian(e2, axis=0, keepdims=True) / CHI2_3_MEDIAN
    step = (np.diff(z, 2, axis=0) ** 2).sum(axis=-1)
    jitter = np.nanmedian(step, axis=0, keepdims=True) / CHI2_3_MEDIAN
    return np.maximum(np.maximum(r, typical), jitter)


def _residual_weights(z: np.ndarray, r: np.ndarray, track: np.ndarray) -> np.ndarray:
    """(T, K) Student-t weights of the measurements from their residuals to the track.

    ``d2`` sums the three axes' squared residuals over the white variance ``r``. A gross
    outlier is a spike (:func:`_spikes`) whose squared residual exceeds ``GROSS_D2`` times
    the residual scale (:func:`_residual_scale`), so that neither a white scale fitted
    small nor a fast step turns real movement into outliers. Gross outliers and missing
    measurements get weight 0.
    """
    e2 = ((z - track) ** 2).sum(axis=-1)
    gross = (e2 > GROSS_D2 * _residual_scale(z, r, e2)) & _spikes(z)
    w = np.where(gross, 0.0, (NU + 3) / (NU + e2 / r))
    return np.nan_to_num(w, nan=0.0)


def _lagging_scale(
    z: np.ndarray, r: np.ndarray, track: np.ndarray, dt: np.ndarray, params: SmootherParams
) -> np.ndarray:
    """(T, K, 3) factor on the process noise where the smoothed track lags the predictions.

    A residual beyond :data:`LAG_D2` times the residual scale (:func:`_residual_scale`)
    that is no spike (:func:`_spikes`) is a movement faster than the model (a paw's
    sudden step), not an outlier: the process noise of that frame and its neighbours is
    raised to :data:`ADAPT_BOOST` times what lets the track move by the residual within a
    frame, and the next pass follows the step.
    """
    e = z - track
    e2 = (e**2).sum(axis=-1)
    with np.errstate(invalid="ignore"):
        lag = (e2 > LAG_D2 * _residual_scale(z, r, e2)) & ~_spikes(z)
    h = np.concatenate([dt[1:], dt[-1:]])[:, None, None]
    need = ADAPT_BOOST * 3 * np.nan_to_num(e) ** 2 / h**3 / params.q[None, :, None]
    scale = np.clip(np.where(lag[..., None], need, 1.0), 1.0, MAX_Q_SCALE)
    wide = np.pad(scale, ((1, 1), (0, 0), (0, 0)), constant_values=1.0)
    return np.lib.stride_tricks.sliding_window_view(wide, 3, axis=0).max(axis=-1)


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
            movements are followed rather than damped.

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
    p = params.arrays()
    scale = adaptive_q_scale(z, conf, dt, params) if adaptive else np.ones(z.shape)
    qs = scale if adaptive else None
    run = forward(z, conf, dt, p, keep=True, q_scale=qs)
    mean, cov = rts(run.states, dt, p)
    r = _meas_var_frames(conf, params)
    for _ in range(IRLS_PASSES):
        track = mean[..., 0] + mean[..., 2]
        if qs is not None:
            qs = np.maximum(qs, _lagging_scale(z, r, track, dt, params))
        w = _residual_weights(z, r, track)
        mean, cov = rts(forward(z, conf, dt, p, True, q_scale=qs, weights=w).states, dt, p)
    scale = scale if qs is None else qs
    track = cov[..., 0, 0] + 2 * cov[..., 0, 2] + cov[..., 2, 2]
    # the position reported is the smoothed track: the correlated error that the
    # recording cannot tell from movement stays in it, and its band covers the estimate
    return SmoothResult(
        mean=mean[..., 0] + mean[..., 2],
        std=np.sqrt(np.maximum(cov[..., 0, 0], 0.0) + mean[..., 2] ** 2),
        track_std=np.sqrt(np.maximum(track, 0.0)),
        offset=mean[..., 2],
        filled=~valid,
        rejected=valid & (w == 0),
        weight=w,
        params=params,
        loglik=loglik,
        q_scale=scale,
    )


def misfit_warning(res: SmoothResult, keypoints: tuple[str, ...]) -> str | None:
    """The keypoints with more than :data:`MISFIT_REJECTED` of their predictions rejected.

    The model leaves out at most about 0.1 % of what it describes as gross outliers; far more
    means that it does not describe the keypoint's predictions (a network that loses the
    keypoint often, or motion the model cannot follow). Returns the warning, or None.
    """
    frac = res.rejected.sum(axis=0) / np.maximum((~res.filled).sum(axis=0), 1)
    bad = [f"{k} {100 * f:.0f} %" for k, f in zip(keypoints, frac, strict=True)]
    bad = [b for b, f in zip(bad, frac, strict=True) if f > MISFIT_REJECTED]
    return None if not bad else (
        f"the smoother left out more than {100 * MISFIT_REJECTED:.0f} % of the predictions "
        f"of {len(bad)} keypoints as gross outliers ({', '.join(bad)}; its model expects "
        "at most about 0.1 %): the model fitted on the recording does not describe them, and the "
        "smoothed track may have dropped real movements; compare it with the raw poses "
        "before analysing it"
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
    gross outliers left out, ``extra/smooth_weight`` (T, K) every prediction's Student-t
    weight and ``extra/smooth_offset`` (T, K, 3) the estimated correlated error of the
    network (mm); the confidences stay the network's. The provenance
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

    Poses with an animal axis are smoothed animal by animal (each animal's own fit); the
    provenance's ``smoother`` then holds the shared settings and ``animals``: per animal its
    fitted parameters, rejected count and any warning.

    Raises:
        SmoothingError: too few predicted frames (of any animal), or ``bones`` without
            usable limbs.
    """
    if data.individuals is not None:
        return _smooth_animals(data, source, error_floor, bones)
    res = smooth_arrays(data.poses, data.confidence, frame_intervals(data.frame_index, data.fps))
    floor, persistent = _persistent(error_floor, data.keypoints)
    std = np.sqrt(res.std**2 + floor[None] ** 2)
    mean, bone_entry = res.mean, None
    if bones:
        mean, bone_entry = _bones(data, res.mean, res.std**2)
    prov: dict[str, Any] = dict(data.provenance)
    prov["smoother"] = {
        "method": "constant-velocity position + correlated (Ornstein-Uhlenbeck) network "
        "error + white Student-t error; Kalman filter + RTS smoother (freipose.predict.smooth)",
        "measurement": "position + offset (sd offset_sd_mm, correlation time offset_tau_s) "
        "+ white Student-t error of scale sigma0 (one per keypoint; beta = 0: the confidence "
        "does not scale it)",
        "student_t_dof": NU,
        "reweighting_passes": IRLS_PASSES,
        "gross_outlier_d2": GROSS_D2,
        "rejected": int(res.rejected.sum()),
        "adaptive_process_noise": {
            "window_frames": ADAPT_WINDOW,
            "threshold": ADAPT_THRESHOLD,
            "boost": ADAPT_BOOST,
            "frames_raised": int(res.q_raised),
        },
        "fitted_by": "maximum Student-t innovation likelihood on the recording",
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
        "smooth_weight": res.weight.astype(np.float32),
        "smooth_offset": res.offset.astype(np.float32),
    }
    return dataclasses.replace(data, poses=mean.astype(np.float32), provenance=prov, extra=extra)


def _smooth_animals(
    data: PoseData, source: str, error_floor: np.ndarray | HeldOutError | None, bones: bool
) -> PoseData:
    """:func:`smooth_poses` of each animal of poses (T, A, K, 3), joined again."""
    done = {}
    for name in data.individuals or ():
        try:
            done[name] = smooth_poses(data.animal(name), f"{source} ({name})", error_floor, bones)
        except SmoothingError as exc:
            raise SmoothingError(f"animal {name}: {exc}") from exc
    out = stack_animals(done, data.identity_confidence)
    per_animal = {n: d.provenance["smoother"] for n, d in done.items()}
    first = next(iter(per_animal.values()))
    own = ("params", "rejected", "warning", "adaptive_process_noise", "bones", "source")
    shared = {k: v for k, v in first.items() if k not in own}
    animals = {n: {k: e[k] for k in own if k in e} for n, e in per_animal.items()}
    prov = {**dict(data.provenance), "smoother": {**shared, "source": source, "animals": animals}}
    return dataclasses.replace(out, provenance=prov)


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
