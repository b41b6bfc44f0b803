"""Statistics of the attribution.

Informative columns, per-recording z-scores, balanced
accuracy and macro F1 of binary predictions, and chi-squared tests of predicted vs. true
classes, with every frame counted as independent or with the effective number of
independent frames of two autocorrelated series.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np


def is_informative(mean: np.ndarray, std: np.ndarray, rtol: float) -> np.ndarray:
    """Tell which columns vary beyond numerical noise.

    A column with this mean and standard deviation is informative when
    ``std > rtol * sqrt(mean² + std²)`` (never for constant and all-NaN columns).

    Args:
        mean: (V,) or scalar column means.
        std: (V,) or scalar column standard deviations.
        rtol: the largest ratio of deviation to root mean square that counts as constant.

    Returns:
        (V,) or scalar bool.
    """
    mean = np.asarray(mean, dtype=np.float64)
    std = np.asarray(std, dtype=np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        rms = np.sqrt(mean**2 + std**2)
        return np.isfinite(std) & np.isfinite(rms) & (std > rtol * rms)


def informative_columns(x: np.ndarray, rtol: float = 1e-5) -> np.ndarray:
    """Find the columns of ``x`` that can be standardized.

    Such a column has at least two finite values whose standard deviation exceeds ``rtol``
    times their root mean square. A column below that is constant up to float round-off
    (e.g. the distance of a rigidly attached keypoint to the local origin);
    ``StandardScaler`` would divide by the round-off and turn any offset of that column
    between recordings into huge z-scores.

    Args:
        x: (N, V) values (NaN allowed).
        rtol: see :func:`is_informative`.

    Returns:
        (V,) bool.
    """
    x = np.asarray(x, dtype=np.float64)
    n = np.isfinite(x).sum(axis=0)
    mean = np.zeros(x.shape[1])
    std = np.zeros(x.shape[1])
    ok = n >= 2
    if ok.any():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            mean[ok] = np.nanmean(x[:, ok], axis=0)
            std[ok] = np.nanstd(x[:, ok], axis=0)
    return ok & is_informative(mean, std, rtol)


def standardize_recording(values: np.ndarray, rtol: float = 1e-5) -> np.ndarray:
    """Z-score every column of one recording with its own mean and deviation (NaN ignored).

    Columns constant up to round-off (:func:`is_informative`) become 0.

    Args:
        values: (T, V) variables of one recording.
        rtol: see :func:`is_informative`.

    Returns:
        (T, V) float64.
    """
    x = np.asarray(values, dtype=np.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = np.nanmean(x, axis=0)
        std = np.nanstd(x, axis=0)
    ok = is_informative(mean, std, rtol)
    z = (x - np.where(ok, mean, 0.0)) / np.where(ok, std, 1.0)
    return np.where(ok, z, np.where(np.isfinite(x), 0.0, np.nan))


def confusion(y_true: np.ndarray, y_pred: np.ndarray) -> np.ndarray:
    """Count true vs. predicted classes.

    Args:
        y_true: (N,) labels in {0, 1}.
        y_pred: (N,) predictions in {0, 1}.

    Returns:
        (2, 2) float counts: rows = true class (0, 1), columns = predicted class.
    """
    idx = 2 * np.asarray(y_true, dtype=np.int64) + np.asarray(y_pred, dtype=np.int64)
    return np.bincount(idx, minlength=4)[:4].reshape(2, 2).astype(float)


def chi2_pvalue(table: np.ndarray, n_effective: float | None = None) -> float:
    """Test a 2x2 table of true vs. predicted classes (Pearson's chi-squared, Yates-corrected).

    The statistic of ``scipy.stats.chi2_contingency`` on a 2x2 table (one degree of
    freedom, Yates' continuity correction), computed directly: the single-variable tests
    run it hundreds of times per group, and scipy's generic wrapper costs more than the
    arithmetic.

    Args:
        table: (2, 2) counts.
        n_effective: when given, the table is scaled to this many frames first (the
            effective number of independent frames, see :func:`effective_frames`).

    Returns:
        The p-value; 1 when a row or column is empty (a classifier that always predicts
        one class shows no association).
    """
    from scipy.special import chdtrc

    table = np.asarray(table, dtype=float)
    n = table.sum()
    if n == 0 or (table.sum(axis=0) == 0).any() or (table.sum(axis=1) == 0).any():
        return 1.0
    if n_effective is not None:
        table = table * (min(n_effective, n) / n)
    expected = np.outer(table.sum(axis=1), table.sum(axis=0)) / table.sum()
    diff = expected - table
    observed = table + np.minimum(0.5, np.abs(diff)) * np.sign(diff)
    stat = float(np.sum((observed - expected) ** 2 / expected))
    return float(chdtrc(1, stat))


def table_scores(table: np.ndarray) -> tuple[float, float]:
    """Score a (2, 2) true-by-predicted table.

    Args:
        table: (2, 2) counts, rows = true class, columns = predicted class.

    Returns:
        (balanced accuracy, macro F1).
    """
    (tn, fp), (fn, tp) = np.asarray(table, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        recalls = [tn / (tn + fp) if tn + fp else np.nan, tp / (tp + fn) if tp + fn else np.nan]
        ba = float(np.nanmean(recalls)) if not np.isnan(recalls).all() else float("nan")
    f_pos = 2 * tp / (2 * tp + fp + fn) if (2 * tp + fp + fn) else 0.0
    f_neg = 2 * tn / (2 * tn + fp + fn) if (2 * tn + fp + fn) else 0.0
    return ba, float((f_pos + f_neg) / 2)


def autocorrelation(x: np.ndarray, max_lag: int) -> np.ndarray:
    """Autocorrelation of a series at lags 1..max_lag (FFT; biased estimator).

    Args:
        x: (N,) series.
        max_lag: the largest lag.

    Returns:
        (max_lag,) correlations (zeros for a constant series).
    """
    x = np.asarray(x, dtype=float) - np.mean(x)
    n = len(x)
    var = float(x @ x)
    if var <= 0 or max_lag < 1:
        return np.zeros(max(max_lag, 0))
    size = 1 << int(np.ceil(np.log2(2 * n)))
    f = np.fft.rfft(x, size)
    ac = np.fft.irfft(f * np.conj(f), size)[1 : max_lag + 1]
    return ac / var


def effective_frames(
    y_true: np.ndarray, y_pred: np.ndarray, segments: np.ndarray, max_lag_fraction: float = 0.2
) -> float:
    """Effective number of independent frames for a test of association of two series.

    For two autocorrelated series (Bartlett 1935; Pyper & Peterman 1998) this is
    ``n / (1 + 2 Σ_k ρ_true(k) ρ_pred(k))`` per recording, lags up to a fifth of its length,
    summed over recordings. Consecutive video frames are far from independent (and the STFT
    variables are smooth over a whole window), so a chi-squared test that counts every frame
    as independent declares unrelated variables significant; this is the correction.

    Args:
        y_true: (N,) labels in time order, recordings concatenated.
        y_pred: (N,) predictions in the same order.
        segments: lengths of the recordings' parts (sum N).
        max_lag_fraction: the largest lag as a fraction of a part's length.

    Returns:
        The effective number of frames (at most N).
    """
    total = 0.0
    a = 0
    for n in np.asarray(segments, dtype=int):
        yt, yp = y_true[a : a + n], y_pred[a : a + n]
        a += n
        if n < 3:
            total += n
            continue
        lag = max(1, int(n * max_lag_fraction))
        deff = 1.0 + 2.0 * float(autocorrelation(yt, lag) @ autocorrelation(yp, lag))
        total += n / min(max(deff, 1.0), n)
    return total


def scores(
    y_true: np.ndarray, y_pred: np.ndarray, segments: np.ndarray | None = None
) -> tuple[float, float, float, float, float]:
    """Score binary predictions in time order.

    Args:
        y_true: (N,) labels in {0, 1}.
        y_pred: (N,) predictions in {0, 1}.
        segments: lengths of the recordings' parts (sum N); None: one recording.

    Returns:
        balanced accuracy, macro F1, chi-squared p with every frame counted as independent
        (the method's test), effective number of frames, chi-squared p on that number; on
        no frames every score and p-value is NaN (no test) and the effective number 0.
    """
    y_true = np.asarray(y_true).astype(np.int64)
    y_pred = np.asarray(y_pred).astype(np.int64)
    if len(y_true) == 0:
        nan = float("nan")
        return nan, nan, nan, 0.0, nan
    table = confusion(y_true, y_pred)
    ba, f1 = table_scores(table)
    seg = np.array([len(y_true)]) if segments is None else segments
    n_eff = effective_frames(y_true, y_pred, seg)
    return ba, f1, chi2_pvalue(table), n_eff, chi2_pvalue(table, n_eff)


@dataclass(frozen=True)
class MeanSem:
    """Mean over trials at every time step.

    Attributes:
        mean: (L,) mean over the trials (NaN ignored).
        sem: (L,) standard error of the mean (NaN with fewer than two trials).
        n: (L,) number of finite trials.
    """

    mean: np.ndarray
    sem: np.ndarray
    n: np.ndarray


def mean_sem(trials: np.ndarray) -> MeanSem:
    """Mean and standard error over trials.

    Args:
        trials: (N, L) values of N trials (NaN allowed).

    Returns:
        The (L,) mean, standard error and trial count.
    """
    n = np.isfinite(trials).sum(axis=0)
    with warnings.catch_warnings(), np.errstate(invalid="ignore", divide="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = np.nanmean(trials, axis=0)
        sd = np.nanstd(trials, axis=0, ddof=1)
    sem = np.where(n > 1, sd / np.sqrt(np.maximum(n, 1)), np.nan)
    return MeanSem(mean, sem, n)
