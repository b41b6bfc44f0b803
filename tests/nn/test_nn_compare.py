"""Paired comparison of two results' errors on the same held-out instants."""

from __future__ import annotations

import numpy as np
import pytest

from freipose.nn.compare import paired_difference


def _errors(n: int = 100, k: int = 6, seed: int = 0) -> np.ndarray:
    """(n, k) errors that drift slowly over time, as consecutive frames' errors do."""
    rng = np.random.default_rng(seed)
    drift = np.cumsum(rng.normal(0, 0.3, n))[:, None]
    return np.abs(3.0 + drift + rng.normal(0, 1.0, (n, k)))


def test_a_clearly_better_result_is_lower_and_equal_ones_are_not_distinguishable():
    b = _errors()
    better = paired_difference(0.7 * b, b, "a", "b")
    assert better is not None and better.verdict == "lower"
    assert better.high < 0 and better.win_rate == 1.0 and better.instants == 100
    assert better.difference == pytest.approx(-0.3 * np.median(b))
    assert better.block == 10
    same = paired_difference(b, b.copy(), "a", "b")
    assert same is not None and same.verdict == "not distinguishable"
    assert same.difference == same.low == same.high == 0.0
    rng = np.random.default_rng(4)
    noisy = paired_difference(b + rng.normal(0, 0.05, b.shape), b, "a", "b")
    assert noisy is not None and noisy.low < 0 < noisy.high
    worse = paired_difference(b + 1.0, b, "x", "y")
    assert worse is not None and worse.verdict == "higher" and worse.low > 0
    assert worse.to_dict()["verdict"] == "higher"
    assert worse.mean_verdict == "higher" and worse.mean_difference == pytest.approx(1.0)
    assert "x vs y: median " in worse.sentence() and ": higher; mean " in worse.sentence()
    assert better.mean_difference == pytest.approx(-0.3 * b.mean())
    assert better.mean_low <= better.mean_difference <= better.mean_high < 0


def test_the_mean_sees_large_errors_on_few_keypoints_that_the_median_does_not():
    a = _errors(120, k=10)
    b = a.copy()
    b[:, 9] += 20.0  # b loses one keypoint (a hidden paw) by 2 cm, a finds it
    got = paired_difference(a, b, "a", "b")
    assert got is not None
    assert got.mean_verdict == "lower" and got.mean_difference == pytest.approx(-2.0)
    assert abs(got.difference) < 0.5  # the median of ten keypoints hardly moves
    assert got.win_rate == 1.0
    assert got.to_dict()["mean_verdict"] == "lower"


def test_only_instants_both_were_evaluated_on_count_and_missing_predictions_lose():
    b = _errors(40)
    a = b - 0.5
    a[:10] = np.nan  # unlabeled instants (NaN in both would be the same)
    b[:10] = np.nan
    a[10:, 0] = np.inf  # a gave no prediction of keypoint 0: an infinite error
    got = paired_difference(a, b, "a", "b")
    assert got is not None and got.instants == 30
    assert got.win_rate == 0.0  # the infinite errors make every instant's mean worse
    assert got.missed_a == 30 and got.missed_b == 0
    assert got.mean_difference == pytest.approx(-0.5)  # the means skip the missed keypoints
    assert "no prediction: 30 keypoints of a, 0 of b" in got.sentence()
    assert paired_difference(np.full((3, 2), np.nan), np.ones((3, 2)), "a", "b") is None
    with pytest.raises(ValueError, match="one shape"):
        paired_difference(np.ones((3, 2)), np.ones((3, 3)), "a", "b")
