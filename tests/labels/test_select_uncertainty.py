"""labels select ranks frames by the network's calibrated uncertainty where the poses carry it."""

from __future__ import annotations

import numpy as np

from freipose.io.poses import PoseData
from freipose.labels.select import select_frames


def _poses(uncertainty=None):
    rng = np.random.default_rng(0)
    T, K = 60, 4
    poses = rng.normal(0, 30, (T, K, 3)).astype(np.float32)
    conf = np.full((T, K), 0.9, np.float32)
    conf[10] = 0.2  # the least confident frame
    poses[50] = np.nan  # not found
    conf[50] = 0.0
    extra = {} if uncertainty is None else {"uncertainty": uncertainty}
    return PoseData(poses, conf, tuple("abcd"), np.arange(T), 30.0, (0.0, 0.0, 1.0), extra=extra)


def test_uncertainty_outranks_confidence_and_not_found_frames_come_first():
    unc = np.full((60, 4), 2.0, np.float32)
    unc[30] = 9.0  # confident, but its views disagree
    unc[50] = np.nan
    sel = select_frames(_poses(unc), 3, min_gap=2)
    # the most uncertain frame weighs as much as a frame where the animal was lost
    assert set(sel.frame_index[:2]) == {30, 50}
    assert sel.uncertainty[list(sel.frame_index).index(30)] == 9.0
    # the confidences alone pick the least confident frame after the lost one
    plain = select_frames(_poses(), 3, min_gap=2)
    assert list(plain.frame_index[:2]) == [50, 10] and 30 not in plain.frame_index
    assert np.isnan(plain.uncertainty).all()


def test_unknown_uncertainty_falls_back_to_confidence():
    sel = select_frames(_poses(np.full((60, 4), np.nan, np.float32)), 2, min_gap=2)
    assert list(sel.frame_index) == [50, 10]
