"""benchmarks/smooth_ensembles.py: the figures of several predictions per frame."""

from __future__ import annotations

import numpy as np

from freipose.io.poses import PoseData

BENCHMARK = "smooth_ensembles"  # the script the conftest fixture ``bench`` loads


def _walk(n: int = 200, k: int = 3, seed: int = 0) -> np.ndarray:
    """(n, k, 3) a slow smooth movement in mm."""
    t = np.arange(n)[:, None, None] / 25.0
    phase = np.random.default_rng(seed).uniform(0, 6, (1, k, 3))
    return 20 * np.sin(2 * np.pi * 0.3 * t + phase)


def test_error_figures_of_the_truth_are_zero_and_of_an_offset_are_the_offset(bench):
    truth = _walk()
    assert bench.error_figures(truth, truth, 25.0) == {
        "median_jpe_mm": 0.0, "mean_jpe_mm": 0.0, "velocity_error_mm_s": 0.0}  # fmt: skip
    f = bench.error_figures(truth + np.array([3.0, 4.0, 0.0]), truth, 25.0)
    assert np.isclose(f["median_jpe_mm"], 5.0) and np.isclose(f["mean_jpe_mm"], 5.0)
    assert f["velocity_error_mm_s"] < 1e-9  # a constant offset does not move


def test_member_correlation_tells_shared_errors_from_independent_ones(bench):
    rng = np.random.default_rng(1)
    truth = _walk()
    shared = rng.normal(0, 2, truth.shape)
    same = np.stack([truth + shared + rng.normal(0, 0.1, truth.shape) for _ in range(4)])
    apart = np.stack([truth + rng.normal(0, 2, truth.shape) for _ in range(4)])
    hi, lo = bench.member_correlation(same, truth), bench.member_correlation(apart, truth)
    assert hi["error_correlation"] > 0.99 and hi["error_change_correlation"] > 0.99
    assert abs(lo["error_correlation"]) < 0.1 and abs(lo["error_change_correlation"]) < 0.1


def test_the_mean_of_independent_members_lowers_the_velocity_error(bench):
    rng = np.random.default_rng(2)
    truth = _walk(n=300)
    members = np.stack([truth + rng.normal(0, 1.0, truth.shape) for _ in range(8)])
    conf = np.ones(truth.shape[:2], np.float32)
    raw = PoseData(poses=members[0].astype(np.float32), confidence=conf,
                   keypoints=("a", "b", "c"), frame_index=np.arange(300), fps=25.0)  # fmt: skip
    f = bench.compare(raw, truth, {"8 members": bench.with_smoothed(raw, members.mean(0), conf)})
    assert f["single"]["velocity_ratio"] == 1.0
    # independent errors: the mean of 8 has about 1/sqrt(8) of one member's
    assert 0.25 < f["8 members"]["velocity_ratio"] < 0.5
    assert f["8 members"]["median_jpe_mm"] < 0.5 * f["single"]["median_jpe_mm"]
    assert f["single, smoothed"]["velocity_ratio"] < 1.0  # white errors: the smoother helps


def test_summary_gives_each_figure_its_range_over_the_runs_of_its_kind(bench):
    def run(kind: str, single: float, smoothed: float, corr: float) -> dict:
        name = "8 members, smoothed" if kind == "tta" else "ensemble of demos, smoothed"
        f = {"single": {"median_jpe_mm": single, "velocity_ratio": 1.0},
             "single, smoothed": {"median_jpe_mm": single, "velocity_ratio": 0.9},
             name: {"median_jpe_mm": smoothed, "velocity_ratio": 0.8},
             "error_correlation": corr, "error_change_correlation": corr - 0.1}  # fmt: skip
        return {"kind": kind, "figures": f}

    runs = [run("tta", 4.0, 3.9, 0.95), run("tta", 3.0, 3.2, 0.97), run("ensemble", 4.0, 4.0, 0.9)]
    s = bench.summarize(runs)
    jpe = s["TTA mean smoothed, median JPE change mm"]
    assert np.isclose(jpe["min"], -0.1) and np.isclose(jpe["max"], 0.2)
    assert s["TTA members' error correlation"] == {"min": 0.95, "max": 0.97}
    assert s["demos' error correlation"] == {"min": 0.9, "max": 0.9}
    assert s["single network smoothed, velocity x single"] == {"min": 0.9, "max": 0.9}
