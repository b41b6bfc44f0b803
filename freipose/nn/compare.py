"""Is one network's error really lower than another's on the same held-out instants?

Two medians of joint position errors a tenth of a millimetre apart can swap with another
held-out block. :func:`paired_difference` compares two results on the instants both were
evaluated on: the difference of their median JPE, an interval for it from a moving-block
bootstrap over the instants in their stored order (by session, then time: consecutive
instants are near-copies, so they are resampled in blocks of about ``sqrt(N)`` instants
and never one by one), and the share of instants on which the first has the lower mean
error. An interval that contains 0 says the data cannot tell the two apart.
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
        level: the interval's coverage (0.95).
        win_rate: share of instants where ``a``'s mean error over the keypoints is lower.
        instants: shared instants.
        block: instants per bootstrap block.
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

    @property
    def verdict(self) -> str:
        """``"lower"``, ``"higher"`` or ``"not distinguishable"`` (``a`` against ``b``)."""
        if self.high < 0:
            return "lower"
        if self.low > 0:
            return "higher"
        return "not distinguishable"

    def to_dict(self) -> dict[str, float | int | str]:
        """The fields and the verdict as JSON-able values."""
        d: dict[str, float | int | str] = dict(self.__dict__)
        d["verdict"] = self.verdict
        return d

    def sentence(self) -> str:
        """One line for the console."""
        return (
            f"{self.a} vs {self.b}: {self.median_a:.2f} vs {self.median_b:.2f} mm, "
            f"{self.difference:+.2f} mm ({round(100 * self.level)} % interval {self.low:+.2f} "
            f"to {self.high:+.2f}), lower on {100 * self.win_rate:.0f} % of the instants: "
            f"{self.verdict}"
        )


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
    med_a, med_b = _median(ea, both), _median(eb, both)
    rng = np.random.default_rng(seed)
    starts = rng.integers(0, n - block + 1, size=(resamples, math.ceil(n / block)))
    idx = (starts[..., None] + np.arange(block)).reshape(resamples, -1)[:, :n]
    boot = np.array([_median(ea[i], both[i]) - _median(eb[i], both[i]) for i in idx])
    tail = (1 - LEVEL) / 2
    low, high = np.quantile(boot, [tail, 1 - tail])
    # per instant, the mean error over the keypoints both have (every kept row has one)
    mean_a = np.where(both, ea, 0).sum(1) / both.sum(1)
    mean_b = np.where(both, eb, 0).sum(1) / both.sum(1)
    return PairedDifference(
        a=a,
        b=b,
        median_a=med_a,
        median_b=med_b,
        difference=med_a - med_b,
        low=float(low),
        high=float(high),
        level=LEVEL,
        win_rate=float(np.mean(mean_a < mean_b)),
        instants=n,
        block=int(block),
    )


def _median(errors: np.ndarray, mask: np.ndarray) -> float:
    """Median of the masked errors (``inf`` counts as the largest)."""
    return float(np.median(errors[mask]))
