"""benchmarks/classifier_days.py: the full classifier trained on one day or another."""

from __future__ import annotations

import pytest

from freipose.analysis.config import AttributionConfig
from freipose.analysis.simulate import (
    StimulusEffect,
    simulate_rat,
    stimulation_windows,
    write_events_csv,
)
from freipose.analysis.variables import VariableConfig
from freipose.io.poses import write_poses_h5

BENCHMARK = "classifier_days"  # the script the conftest fixture ``bench`` loads


@pytest.fixture(scope="module")
def days(tmp_path_factory, bench):
    """Three simulated 30 s days of a rat whose right front paw oscillates at 5 Hz."""
    folder = tmp_path_factory.mktemp("days")
    effect = StimulusEffect("Paw Front Right", frequency_hz=5.0, amplitude_mm=30.0)
    recs = []
    for k in range(3):
        win = stimulation_windows(30.0, 1.0, 4.0, 2.0, 0.0, seed=k)
        data = simulate_rat(30.0, 25.0, win, effect, seed=k, noise_mm=1.0)
        write_poses_h5(data, folder / f"day{k}.poses.h5")
        write_events_csv(win, folder / f"day{k}.csv")
        recs.append(bench.Recording(f"day{k}", folder / f"day{k}.poses.h5", folder / f"day{k}.csv"))
    return folder, recs


def test_train_sets_are_the_labeled_day_each_other_day_and_all_others(bench, days):
    _, (a, b, c) = days
    assert bench.train_sets(a, [b, c]) == [[a], [b], [c], [b, c]]
    assert bench.train_sets(a, [b]) == [[a], [b]]


def test_score_reads_the_full_classifier_and_the_best_single_variable(bench, days):
    folder, (a, b, c) = days
    acfg = AttributionConfig(onset_delay_s=0.6, margin_s=0.5, pre_s=1.0, post_s=1.0)
    s = bench.score(folder / "study", [a, b], c, acfg, VariableConfig(stft_window=32))
    assert s.train == ("day0", "day1")
    assert 'split = "test"' in (folder / "study" / "study.toml").read_text()
    assert 0.7 < s.balanced_accuracy <= s.train_balanced_accuracy <= 1.0
    assert "Paw Front Right" in s.best_variable and s.best_variable_accuracy > 0.8
