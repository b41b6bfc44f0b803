"""Is one network's error really lower than another's on the same held-out instants?

Two medians of joint position errors a tenth of a millimetre apart can swap with another
held-out block. :func:`paired_difference` compares two results on the instants both were
evaluated on: the difference of their median JPE and of their mean JPE, an interval for
each from a moving-block bootstrap over the instants in their stored order (by session,
then time: consecutive instants are near-copies, so they are resampled in blocks of about
``sqrt(N)`` instants and never one by one), and the share of instants on which the first
has the lower mean error. An interval that contains 0 says the data cannot tell the two
apart.

The median shows the typical keypoint; the mean (the MPJPE of DANNCE and JARVIS) also
weighs the large errors, such as a hidden paw placed a few centimetres off, which the
median of many easy keypoints does not see. Both are reported, each with its verdict.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

RESAMPLES = 2000
LEVEL = 0.95


@dataclass(frozen=True)
class PairedDifference:
    """Result ``a`` against result ``b`` on the same instants (mm).

    Attributes:
        a: name of the first result.
        b: name of the second result.
        median_a: median JPE of ``a`` over the shared instants' keypoints.
        median_b: the same for ``b``.
        difference: ``median_a - median_b`` (negative: ``a`` is better).
        low: lower end of the bootstrap interval of ``difference``.
        high: upper end.
        level: the intervals' coverage (0.95).
        win_rate: share of instants where ``a``'s mean error over the keypoints is lower.
        instants: shared instants.
        block: instants per bootstrap block.
        mean_a: mean JPE of ``a`` over the keypoints both predicted.
        mean_b: the same for ``b``.
        mean_difference: ``mean_a - mean_b``.
        mean_low: lower end of the bootstrap interval of ``mean_difference``.
        mean_high: upper end.
        missed_a: labeled keypoints ``a`` gave no prediction for (infinite errors: they
            count in the medians and the win rate, not in the means).
        missed_b: the same for ``b``.
    """

    a: str
    b: str
    median_a: float
    median_b: float
    difference: float
    low: float
    high: float
    level: float
    win_rate: float
    instants: int
    block: int
    mean_a: float
    mean_b: float
    mean_difference: float
    mean_low: float
    mean_high: float
    missed_a: int
    missed_b: int

    @property
    def verdict(self) -> str:
        """The medians': ``"lower"``, ``"higher"`` or ``"not distinguishable"`` (``a`` vs ``b``)."""
        return _verdict(self.low, self.high)

    @property
    def mean_verdict(self) -> str:
        """The same for the means."""
        return _verdict(self.mean_low, self.mean_high)

    def to_dict(self) -> dict[str, float | int | str]:
        """The fields and the verdicts as JSON-able values."""
        d: dict[str, float | int | str] = dict(self.__dict__)
        d["verdict"] = self.verdict
        d["mean_verdict"] = self.mean_verdict
        return d

    def sentence(self) -> str:
        """One line for the console."""
        level = round(100 * self.level)
        missed = (
            f" (no prediction: {self.missed_a} keypoints of {self.a}, {self.missed_b} of "
            f"{self.b}; not in the means)"
            if self.missed_a or self.missed_b
            else ""
        )
        return (
            f"{self.a} vs {self.b}: median {self.median_a:.2f} vs {self.median_b:.2f} mm, "
            f"{self.difference:+.2f} ({level} % interval {self.low:+.2f} to {self.high:+.2f}): "
            f"{self.verdict}; mean {self.mean_a:.2f} vs {self.mean_b:.2f} mm, "
            f"{self.mean_difference:+.2f} ({self.mean_low:+.2f} to {self.mean_high:+.2f}): "
            f"{self.mean_verdict}; lower on {100 * self.win_rate:.0f} % of the instants{missed}"
        )


def _verdict(low: float, high: float) -> str:
    """``"lower"`` when the interval lies below 0, ``"higher"`` above, else not distinguishable."""
    if high < 0:
        return "lower"
    if low > 0:
        return "higher"
    return "not distinguishable"


def paired_difference(
    errors_a: np.ndarray,
    errors_b: np.ndarray,
    a: str,
    b: str,
    resamples: int = RESAMPLES,
    seed: int = 0,
) -> PairedDifference | None:
    """Compare two results' joint position errors on the same instants.

    Args:
        errors_a: (N, K) JPE of the first result (mm), NaN where the label is unknown
            (``inf`` where it gave no prediction).
        errors_b: (N, K) the second result's, on the same instants and keypoints.
        a: the first result's name.
        b: the second result's name.
        resamples: bootstrap resamples.
        seed: the bootstrap's random seed.

    Returns:
        The comparison, or None when fewer than 2 instants have an error in both.

    Raises:
        ValueError: the arrays' shapes differ.
    """
    ea, eb = np.asarray(errors_a, np.float64), np.asarray(errors_b, np.float64)
    if ea.shape != eb.shape or ea.ndim != 2:
        raise ValueError(
            f"errors must be two (N, K) arrays of one shape, got {ea.shape}, {eb.shape}"
        )
    both = ~np.isnan(ea) & ~np.isnan(eb)
    rows = np.flatnonzero(both.any(axis=1))
    if len(rows) < 2:
        return None
    ea, eb, both = ea[rows], eb[rows], both[rows]
    n = len(rows)
    block = max(1, round(math.sqrt(n)))
    rng = np.random.default_rng(seed)
    starts = rng.integers(0, n - block + 1, size=(resamples, math.ceil(n / block)))
    idx = (starts[..., None] + np.arange(block)).reshape(resamples, -1)[:, :n]
    med = _median_interval(ea, eb, both, idx)
    mean = _mean_interval(ea, eb, both, idx)
    # per instant, the mean error over the keypoints both have (every kept row has one)
    inst_a = np.where(both, ea, 0).sum(1) / both.sum(1)
    inst_b = np.where(both, eb, 0).sum(1) / both.sum(1)
    return PairedDifference(
        a=a,
        b=b,
        median_a=med[0],
        median_b=med[1],
        difference=med[0] - med[1],
        low=med[2],
        high=med[3],
        level=LEVEL,
        win_rate=float(np.mean(inst_a < inst_b)),
        instants=n,
        block=int(block),
        mean_a=mean[0],
        mean_b=mean[1],
        mean_difference=mean[0] - mean[1],
        mean_low=mean[2],
        mean_high=mean[3],
        missed_a=int((both & np.isinf(ea)).sum()),
        missed_b=int((both & np.isinf(eb)).sum()),
    )


def _median_interval(
    ea: np.ndarray, eb: np.ndarray, both: np.ndarray, idx: np.ndarray
) -> tuple[float, float, float, float]:
    """Both medians and the bootstrap interval of their difference.

    Args:
        ea: (n, K) errors of ``a``.
        eb: (n, K) errors of ``b``.
        both: (n, K) where both have an error.
        idx: (resamples, n) the resampled instants.

    Returns:
        ``(median_a, median_b, low, high)``.
    """
    boot = np.array([_median(ea[i], both[i]) - _median(eb[i], both[i]) for i in idx])
    tail = (1 - LEVEL) / 2
    low, high = np.quantile(boot, [tail, 1 - tail])
    return _median(ea, both), _median(eb, both), float(low), float(high)


def _mean_interval(
    ea: np.ndarray, eb: np.ndarray, both: np.ndarray, idx: np.ndarray
) -> tuple[float, float, float, float]:
    """Both means over the keypoints both predicted and the interval of their difference.

    Same arguments as :func:`_median_interval`; NaN throughout when no keypoint has two
    finite errors.
    """
    finite = both & np.isfinite(ea) & np.isfinite(eb)
    sa, sb = np.where(finite, ea, 0).sum(1), np.where(finite, eb, 0).sum(1)
    cnt = finite.sum(1)
    if not cnt.any():
        return (float("nan"),) * 4
    with np.errstate(invalid="ignore", divide="ignore"):
        boot = (sa[idx].sum(1) - sb[idx].sum(1)) / cnt[idx].sum(1)
    boot = boot[np.isfinite(boot)]
    tail = (1 - LEVEL) / 2
    low, high = np.quantile(boot, [tail, 1 - tail])
    total = cnt.sum()
    return float(sa.sum() / total), float(sb.sum() / total), float(low), float(high)


def _median(errors: np.ndarray, mask: np.ndarray) -> float:
    """Median of the masked errors (``inf`` counts as the largest)."""
    return float(np.median(errors[mask]))
