"""``benchmarks/real_finetune.py`` on the real 8-camera SLEAP session, at a minimal budget."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "sleap-8cam-2mice"


BENCHMARK = "real_finetune"  # the script the conftest fixture ``bench`` loads


@pytest.mark.slow
@pytest.mark.skipif(
    not (DATA / "min_session_frame_groups.slp").is_file(),
    reason=f"the real SLEAP session {DATA} is absent (shared data not mounted)",
)
def test_real_finetune_minimal_budget(bench, tmp_path, capsys):
    pytest.importorskip("sleap_io")
    out = tmp_path / "real"
    args = ["--out", str(out), "--steps", "2", "--preset", "tiny", "--init", "scratch"]
    assert bench.main(args) == 0
    printed = capsys.readouterr().out
    assert "training frames [0, 1] (4 instants), held-out frames [2] (2 instants)" in printed
    res = json.loads((out / "results.json").read_text())
    rows = res["init"]["scratch"]["rows"]
    labels = [label for label, _ in bench.METHODS]
    assert list(rows) == [*labels, "held-out 3D labels themselves"]
    for label in labels:
        assert f"scratch  {label}" in printed
        row = rows[label]
        # 15 + 12 triangulated keypoints of the two mice of the held-out frame
        assert row["n"] == 27 and row["n_2d"] > 2 * row["n"]
        assert math.isfinite(row["jpe_mm"]) and row["jpe_mm"] > 0
        assert math.isfinite(row["reproj_px"]) and row["reproj_px"] > 0
        if label in bench.NETWORKS:  # the error on the training frames, from freipose eval
            assert math.isfinite(row["train_jpe_mm"]) and row["train_jpe_mm"] > 0
    # the triangulated labels reproject near their 2D labels (PROVENANCE: median ~3 px)
    assert rows["held-out 3D labels themselves"]["reproj_px"] < 6
    train = res["init"]["scratch"]["train"]
    seed0 = train["seeds"]["seed0"]
    assert seed0["pose"]["cube_mm"] == seed0["baseline"]["cube_mm"] < 320  # sized for mice
    assert not train["fresh_keypoint_layers"]  # scratch: nothing taken from a base
    assert train["pose_seconds"] > 0 and train["baseline_seconds"] > 0
    # run again: the trained models and the evaluation are reused
    seconds = json.loads((out / "timings.json").read_text())
    assert bench.main(args) == 0
    assert json.loads((out / "timings.json").read_text()) == seconds
    again = json.loads((out / "results.json").read_text())["init"]["scratch"]["rows"]
    assert again == rows
    # the same networks decoded over the whole maps: P0 as before, the 2D points' rows not
    assert bench.main([*args, "--map-window", "0"]) == 0
    assert json.loads((out / "timings.json").read_text()) == seconds  # nothing trained again
    assert (out / "eval" / "scratch" / "seed0" / "map_window0" / "metrics.json").is_file()
    whole = json.loads((out / "results_map_window0.json").read_text())
    assert whole["map_window"] == 0 and "map window 0 (whole maps)" in capsys.readouterr().out
    rows0 = whole["init"]["scratch"]["rows"]
    assert rows0["voxel P0"] == rows["voxel P0"]
    assert rows0["baseline"]["jpe_mm"] != rows["baseline"]["jpe_mm"]


def test_nearest_instant_takes_the_nearest_training_pose(bench):
    pose_a = np.array([[0.0, 0, 0], [10, 0, 0]])
    pose_b = np.array([[0.0, 0, 0], [0, 10, 0]])
    train = np.stack([pose_a, pose_b + 100.0])  # centres (5, 0, 0) and (100, 105, 100)
    gt = np.stack([pose_b + 90.0, pose_a + 1.0])
    ans = bench.nearest_instant(train, gt)
    centres = gt.mean(1, keepdims=True)
    np.testing.assert_allclose(ans[0] - centres[0], pose_b - pose_b.mean(0))
    np.testing.assert_allclose(ans[1] - centres[1], pose_a - pose_a.mean(0))
