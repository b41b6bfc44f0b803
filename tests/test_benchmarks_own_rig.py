"""``benchmarks/own_rig.py``: the own-rig path at a minimal budget, scored against labels
and the exact truth."""

from __future__ import annotations

import json

import pytest

BENCHMARK = "own_rig"  # the script the conftest fixture ``bench`` loads


@pytest.mark.slow
def test_own_rig_minimal_budget(bench, tmp_path, capsys):
    pytest.importorskip("sleap_io")
    out = tmp_path / "own"
    args = ["--out", str(out), "--frames", "40", "--steps", "2", "--preset", "tiny"]
    assert bench.main([*args, "--init", "scratch", "--gap", "3"]) == 0
    printed = capsys.readouterr().out
    assert "held-out labels" in printed and "truth, every kp" in printed
    assert "voxel_P1 - baseline:" in printed and "vs truth, every kp" in printed
    res = json.loads((out / "results.json").read_text())
    seed = res["seeds"]["0"]
    # the truth mapped into the calibration's world lies within the label tool's error
    assert 0 < seed["labels_vs_truth"] < 5.0
    for side in ("labels", "truth", "truth_all"):
        med, mean = seed[side]["median"], seed[side]["mean"]
        assert {"voxel_P1", "baseline", bench.AT_HELD_OUT} <= set(med) & set(mean)
        assert all(c["mean_verdict"] for c in seed[side]["comparisons"])
        assert [(c["a"], c["b"]) for c in seed[side]["comparisons"]] == [
            ("voxel_P1", "baseline"),
            ("voxel_P1", bench.AT_HELD_OUT),
        ]
    # every keypoint of the truth counts at least the labeled ones
    assert seed["truth_all"]["n"] >= seed["truth"]["n"] == seed["labels"]["n"]
    assert set(res["timings"]["seed0"]) == {"train voxel", "train baseline", "eval"}
    # run again: every step is found done, nothing is retrained
    before = (out / "seed0" / "pose" / "model.pt").stat().st_mtime_ns
    assert bench.main([*args, "--init", "scratch", "--gap", "3"]) == 0
    assert (out / "seed0" / "pose" / "model.pt").stat().st_mtime_ns == before
