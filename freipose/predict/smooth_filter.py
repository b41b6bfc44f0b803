"""The state-space model of :mod:`freipose.predict.smooth`: filter, smoother and fit.

Every keypoint and world axis has the state ``(x, v, b)``: the true position ``x`` and
velocity ``v`` follow a constant-velocity model (white-noise acceleration of spectral
density ``q`` in mm^2/s^3), and ``b`` is the network's correlated error, an
Ornstein-Uhlenbeck offset of standard deviation ``offset_sd`` (mm) and correlation time
``offset_tau`` (s) (an AR(1) series with ``phi = exp(-dt / tau)`` from frame to frame). A
frame's measurement is ``z = x + b + e`` with a white error ``e`` of variance
``sigma0^2 * c^-beta`` (``c`` the frame's confidence; the fit sets ``beta = 0``, see
:func:`fit_params`) and Student-t tails of
:data:`NU` degrees of freedom: a measurement whose standardised residual ``d2`` (summed
over the three axes) is large counts with the weight ``(NU + 3) / (NU + d2)`` (its
variance divided by it), so an improbable measurement pulls little without a hard
threshold. Only a gross outlier (``d2`` above :data:`GROSS_D2`, about 0.1 % under the
Student-t model) is left out.

All series (keypoints x axes) and all parameter candidates of the fit run at once as
arrays of 3 x 3 covariances; the loop runs over frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

NU = 5.0  # degrees of freedom of the Student-t measurement error
GROSS_D2 = 100.0  # d2 of a gross outlier: P(d2 > 100) ~ 0.1 % for a 3-dim Student-t, NU=5
MAX_REJECT_RUN = 3
FIT_FRAMES = 4000
MIN_CONFIDENCE = 0.02
_P0 = 1e6  # prior variance of the first position (mm^2) and velocity ((mm/s)^2)
_ROUNDS = 40
MAX_TAU_S = 100.0  # longest correlation time searched (s)


@dataclass(frozen=True)
class SmootherParams:
    """Fitted parameters of the smoother, one value per keypoint.

    Attributes:
        q: (K,) process noise, white-noise acceleration spectral density in mm^2/s^3.
        sigma0: (K,) white measurement standard deviation in mm at confidence 1.
        beta: (K,) exponent of the confidence: variance = sigma0^2 * c^-beta.
        offset_sd: (K,) standard deviation of the correlated error in mm.
        offset_tau: (K,) correlation time of the correlated error in s.
    """

    q: np.ndarray
    sigma0: np.ndarray
    beta: np.ndarray
    offset_sd: np.ndarray
    offset_tau: np.ndarray

    def as_dict(self, keypoints: tuple[str, ...]) -> dict[str, Any]:
        """The parameters per keypoint name, for provenance."""
        rows = zip(keypoints, self.q, self.sigma0, self.beta, self.offset_sd, self.offset_tau,
                   strict=True)  # fmt: skip
        return {
            name: {
                "q_mm2_s3": float(q),
                "sigma0_mm": float(s),
                "beta": float(b),
                "offset_sd_mm": float(o),
                "offset_tau_s": float(tau),
            }  # fmt: skip
            for name, q, s, b, o, tau in rows
        }

    def arrays(self) -> tuple[np.ndarray, ...]:
        """The five parameters as (1, K, 1) arrays, the layout :func:`forward` takes."""
        return tuple(
            np.asarray(a, np.float64)[None, :, None]
            for a in (self.q, self.sigma0, self.beta, self.offset_sd, self.offset_tau)
        )


@dataclass(frozen=True)
class Pass:
    """Forward-filter output.

    Attributes:
        loglik: (G, K) Student-t innovation log-likelihood (up to a constant).
        rejected: (T, K) gross outliers left out (with G = 1; else empty).
        states: filtered means and covariances, predicted means and covariances (if kept).
    """

    loglik: np.ndarray
    rejected: np.ndarray
    states: tuple[np.ndarray, ...]


def _transition(h: float, tau: np.ndarray) -> np.ndarray:
    """(K, 1, 3, 3) transition matrices of a step of ``h`` s, from (K, 1) correlation times."""
    phi = np.exp(-h / tau)
    f = np.zeros((*phi.shape, 3, 3))
    f[..., 0, 0] = f[..., 1, 1] = 1.0
    f[..., 0, 1] = h
    f[..., 2, 2] = phi
    return f


def _cov(c: tuple[np.ndarray, ...]) -> np.ndarray:
    """(..., 3, 3) symmetric matrices from their six entries (xx, xv, xb, vv, vb, bb)."""
    xx, xv, xb, vv, vb, bb = c
    return np.stack([np.stack([xx, xv, xb], -1), np.stack([xv, vv, vb], -1),
                     np.stack([xb, vb, bb], -1)], -2)  # fmt: skip


def _prior(z0: np.ndarray, osd: np.ndarray, shape: tuple[int, ...]):
    """Diffuse state prior at the (K, 3) first measurements: three means, six covariances."""
    zero = np.zeros(shape)
    m = [np.broadcast_to(z0[None], shape).copy(), zero.copy(), zero.copy()]
    big = np.full(shape, _P0)
    return m, [big.copy(), zero.copy(), zero.copy(), big.copy(), zero.copy(),
               np.broadcast_to(osd**2, shape).copy()]  # fmt: skip


def _step_terms(h: float, qa: np.ndarray, osd: np.ndarray, tau: np.ndarray):
    """The prediction's factors for a step of ``h`` s.

    phi, phi^2, the offset's covariance increment and the process noise's three, from
    (G, K, 1) ``qa`` (the process noise of the step), ``osd`` and ``tau``.
    """
    phi = np.exp(-h / tau)
    return (phi, phi * phi, osd**2 * (1 - phi * phi), qa * h**3 / 3, qa * h * h / 2, qa * h)


def _predict(state: tuple[np.ndarray, ...], h: float, terms: tuple[np.ndarray, ...]):
    """The state ``(x, v, b, xx, xv, xb, vv, vb, bb)`` a step of ``h`` s later.

    ``terms``: :func:`_step_terms` of the step.
    """
    x, v, b, xx, xv, xb, vv, vb, bb = state
    phi, phi2, bq, q3, q2, q1 = terms
    return (x + h * v, v, phi * b, xx + 2 * h * xv + h * h * vv + q3, xv + h * vv + q2,
            phi * (xb + h * vb), vv + q1, phi * vb, phi2 * bb + bq)  # fmt: skip


def _online_weights(
    d2: np.ndarray, ok: np.ndarray, full: bool, streak: np.ndarray
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Student-t weights of a frame's measurements from their (G, K) ``d2``.

    A gross outlier (``d2`` above :data:`GROSS_D2`) gets weight 0; after more than
    :data:`MAX_REJECT_RUN` in a row the series restarts at the measurement.

    Returns:
        ``(w, restart, streak)``: the (G, K) weights, where to restart (None: a frame
        with every keypoint measured and none left out) and the updated runs of outliers.
    """
    w = np.where(d2 > GROSS_D2, 0.0, (NU + 3) / (NU + d2))
    gross = ok & (w == 0)
    if full and not gross.any():
        return w, None, np.zeros_like(streak)
    restart = gross & (streak >= MAX_REJECT_RUN)
    return w, restart, np.where(ok, np.where(gross & ~restart, streak + 1, 0), streak)


def _correct(
    state: tuple[np.ndarray, ...], e: np.ndarray, s_eff: np.ndarray, used: np.ndarray
) -> tuple[np.ndarray, ...]:
    """The Kalman correction of the state ``(x, v, b, xx, xv, xb, vv, vb, bb)``.

    Args:
        state: three means and six covariance entries, each (G, K, 3).
        e: (G, K, 3) innovations.
        s_eff: (G, K, 3) innovation variances with the measurements' weights.
        used: (G, K) the measurements that count (elsewhere the state stays).
    """
    x, v, b, xx, xv, xb, vv, vb, bb = state
    hx, hv, hb = xx + xb, xv + vb, xb + bb
    if used.all():
        gx, gv, gb = hx / s_eff, hv / s_eff, hb / s_eff
    else:
        use = used[..., None]
        gx, gv, gb = (np.where(use, g / s_eff, 0.0) for g in (hx, hv, hb))
    return (x + gx * e, v + gv * e, b + gb * e, xx - gx * hx, xv - gx * hv, xb - gx * hb,
            vv - gv * hv, vb - gv * hb, bb - gb * hb)  # fmt: skip


def forward(
    z: np.ndarray,
    conf: np.ndarray,
    dt: np.ndarray,
    params: tuple[np.ndarray, ...],
    keep: bool,
    q_scale: np.ndarray | None = None,
    weights: np.ndarray | None = None,
) -> Pass:
    """Kalman filter of every series and parameter candidate at once.

    The covariance is kept as its six entries (position, velocity, offset), each a
    (G, K, 3) array, so that a step is a few array operations. What does not depend on
    the state (the measurement variances, the prediction's factors for a repeated frame
    interval) is computed once, and a frame where every keypoint is measured and used
    skips the masking.

    Args:
        z: (T, K, 3) measurements in mm, NaN where missing.
        conf: (T, K) confidences (floored) or confidences over a reference.
        dt: (T,) seconds from the previous frame (dt[0] unused).
        params: q, sigma0, beta, offset_sd, offset_tau, each (G, K, 1).
        keep: keep the filtered and predicted states for the smoother.
        q_scale: (T, K, 3) factor on ``q`` in the step into each frame (None: 1).
        weights: (T, K) fixed Student-t weights of the measurements (0: left out); None:
            weighted on line from each innovation, gross outliers left out.
    """
    q, sigma0, beta, osd, tau = params
    t_n, k_n, _ = z.shape
    shape = np.broadcast_shapes(q.shape, (1, k_n, 3))
    valid = np.isfinite(z).all(axis=-1)
    first = np.where(valid.any(axis=0), valid.argmax(axis=0), 0)
    zn = np.nan_to_num(z)
    (x, v, b), (xx, xv, xb, vv, vb, bb) = _prior(zn[first, np.arange(k_n)], osd, shape)
    loglik = np.zeros(shape[:2])
    streak = np.zeros(shape[:2], np.int64)
    rejected = np.zeros((t_n, k_n), bool)
    out: list[list[np.ndarray]] = [[], [], [], []]
    all_valid = valid.all(axis=1)
    counted = valid & (np.arange(t_n)[:, None] > first[None])
    all_counted = counted.all(axis=1)
    r_all = sigma0[None] ** 2 * conf[:, None, :, None] ** (-beta)[None]  # (T, G, K, 1)
    last_h, terms = None, ()
    st = (x, v, b, xx, xv, xb, vv, vb, bb)
    for t in range(t_n):
        if t > 0:
            h = dt[t]
            if q_scale is not None:
                terms = _step_terms(h, q * q_scale[t][None], osd, tau)
            elif h != last_h:  # frames at a constant rate: computed once
                last_h, terms = h, _step_terms(h, q, osd, tau)
            st = _predict(st, h, terms)
        if keep:
            out[2].append(np.stack([a[0] for a in st[:3]], -1))
            out[3].append(_cov(tuple(a[0] for a in st[3:])))
        full = bool(all_valid[t])
        if full or valid[t].any():
            x, v, b, xx, xv, xb, vv, vb, bb = st
            ok = valid[t][None]
            r = r_all[t]  # (G, K, 1)
            base = xx + 2 * xb + bb
            s = base + r
            e = zn[t][None] - x - b
            if not full:
                e = np.where(ok[..., None], e, 0.0)
            d2 = np.add.reduce(e * e / s, axis=-1)
            ll = -0.5 * np.add.reduce(np.log(s), axis=-1) - 0.5 * (NU + 3) * np.log1p(d2 / NU)
            loglik += ll if all_counted[t] else np.where(counted[t][None], ll, 0.0)
            if weights is None:
                w, restart, streak = _online_weights(d2, ok, full, streak)
                used = ok
                if restart is not None:
                    if restart.any():  # a run of gross outliers: the track starts again there
                        m0, p0 = _prior(zn[t], osd, shape)
                        rs = restart[..., None]
                        st = tuple(np.where(rs, n, o) for n, o in zip((*m0, *p0), st, strict=True))
                        w, e = np.where(restart, 1.0, w), np.where(rs, 0.0, e)
                        base = st[3] + 2 * st[5] + st[8]
                    used = ok & (w > 0)
                    rejected[t] = (ok & (w == 0))[0]
            else:
                w = np.broadcast_to(weights[t][None], shape[:2])
                used = ok & (w > 0)
            # after any restart: the covariances of the state with the measurement
            st = _correct(st, e, base + r / np.maximum(w, 1e-12)[..., None], used)
        if keep:
            out[0].append(np.stack([a[0] for a in st[:3]], -1))
            out[1].append(_cov(tuple(a[0] for a in st[3:])))
    return Pass(loglik, rejected, tuple(np.stack(o) for o in out) if keep else ())


def rts(states: tuple[np.ndarray, ...], dt: np.ndarray, params: tuple[np.ndarray, ...]):
    """Rauch-Tung-Striebel pass: (T, K, 3, 3) smoothed means and (T, K, 3, 3, 3) covariances."""
    fm, fp, pm, pp = states
    mean, cov = fm.copy(), fp.copy()
    tau = params[4][0]
    for t in range(len(fm) - 2, -1, -1):
        f = _transition(dt[t + 1], tau)
        # C = P_f F^T P_p^-1, with P_p symmetric: C^T = P_p^-1 F P_f
        c = np.swapaxes(np.linalg.solve(pp[t + 1], f @ fp[t]), -1, -2)
        mean[t] = fm[t] + (c @ (mean[t + 1] - pm[t + 1])[..., None])[..., 0]
        cov[t] = fp[t] + c @ (cov[t + 1] - pp[t + 1]) @ np.swapaxes(c, -1, -2)
    return mean, cov


def _candidates(center: np.ndarray, step: np.ndarray) -> np.ndarray:
    """(4, 9, K): the centre and its two neighbours along each of the 4 coordinates."""
    d = np.vstack([np.zeros(4), np.eye(4), -np.eye(4)])  # (9, 4)
    return center[:, None, :] + d.T[:, :, None] * step[:, None, :]


def _as_params(pts: np.ndarray, h: float) -> tuple[np.ndarray, ...]:
    """(4, G, K) search coordinates -> the five (G, K, 1) parameters (``beta = 0``)."""
    q, s, o, tau = pts
    return (np.exp(q)[..., None], np.exp(s)[..., None], np.zeros_like(q)[..., None],
            np.exp(o)[..., None], np.clip(np.exp(tau), h, MAX_TAU_S)[..., None])  # fmt: skip


def fit_params(
    z: np.ndarray,
    conf: np.ndarray,
    dt: np.ndarray,
) -> tuple[SmootherParams, np.ndarray]:
    """Maximum-likelihood parameters per keypoint, by a compass search.

    The search starts at ``q = 1e5 mm^2/s^3, sigma0 = 2 mm, offset_sd = 2 mm,
    offset_tau = 0.3 s``; every round evaluates the centre and its two neighbours along
    each coordinate (log q, log sigma0, log offset_sd, log offset_tau) and moves to the
    best of them; where the centre is the best, the steps are halved. The likelihood is
    the Student-t one of the on-line weighted filter (:func:`forward`), so gross outliers
    hardly move the fit.

    The white error has one scale per keypoint (``beta = 0``): a pose network's
    confidence falls where a body part takes an unusual pose (a stimulated paw lifted
    and oscillating), so a variance that grows as the confidence falls makes the
    smoother damp exactly those movements; a frame whose prediction is far off counts
    little through its Student-t weight instead.

    Args:
        z: (T, K, 3) measurements in mm, NaN where missing.
        conf: (T, K) confidences in [0, 1], floored at :data:`MIN_CONFIDENCE` (they
            enter only through ``beta``, 0 here).
        dt: (T,) seconds from the previous frame.

    Returns:
        The parameters and the (K,) log-likelihood they reach.
    """
    t_n, k_n, _ = z.shape
    lo = max(0, (t_n - FIT_FRAMES) // 2)
    z, conf, dt = z[lo : lo + FIT_FRAMES], conf[lo : lo + FIT_FRAMES], dt[lo : lo + FIT_FRAMES]
    h = float(np.median(dt[1:])) if len(dt) > 1 else 1.0
    start = [np.log(1e5), np.log(2.0), np.log(2.0), np.log(0.3)]
    center = np.array(start)[:, None] * np.ones((1, k_n))
    step = np.array([np.log(10.0), np.log(10) / 2, np.log(10) / 2, np.log(10) / 2])
    step = step[:, None] * np.ones((1, k_n))
    best_ll = np.full(k_n, -np.inf)
    k = np.arange(k_n)
    for _ in range(_ROUNDS):
        pts = _candidates(center, step)
        ll = forward(z, conf, dt, _as_params(pts, h), keep=False).loglik  # (9, K)
        ll = np.where(np.isfinite(ll), ll, -np.inf)
        i = ll.argmax(axis=0)
        step = np.where((i == 0)[None], step / 2, step)  # no better neighbour: finer steps
        center, best_ll = pts[:, i, k], ll[i, k]
    p = [a[0, :, 0] for a in _as_params(center[:, None, :], h)]
    params = SmootherParams(*p)
    return params, best_ll
