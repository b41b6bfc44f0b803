"""``benchmarks/demo.py``: a finished demo folder recorded as a result with its key figures."""

from __future__ import annotations

import json

import pytest

from freipose.demo.markers import write_marker
from freipose.demo.presets import PRESETS
from freipose.demo.summary import write_summary

BENCHMARK = "demo"  # the script the conftest fixture ``bench`` loads


def _analysis(best: str, part: str, ba: float, significant: int) -> dict:
    """An ``analyze_poses`` result as the demo's analysis step returns it."""
    parts = [part, "Nose", part, "Tail", "Nose", part, "Nose", "Nose", "Tail", "Nose"]
    top = [{"variable": best if i == 0 else f"v{i}", "part": p, "f1": 0.9 - i / 100,
            "p_value": 0.01, "p_adjusted": 0.5, "significant": False}
           for i, p in enumerate(parts)]  # fmt: skip
    return {
        "balanced_accuracy": ba,
        "stimulated_best_rank": 1,
        "classification": [{"balanced_accuracy": ba}],
        "top_variables": top,
        "top10_share_stimulated_part": 0.3,
        "significant": significant,
    }


@pytest.fixture
def finished_demo(tmp_path):
    """A demo folder with the markers of every step that feeds the figures, and its summary."""
    preset = PRESETS["tiny"].with_seed(2)
    out = tmp_path / "demo_seed2"
    part = "Paw Front Right"
    steps = {
        "synth": ({}, 10.0),
        "calibrate": ({"summary": {"max_center_mm": 1.5, "max_rotation_deg": 0.05,
                                   "max_focal_percent": 0.1, "max_rms_px": 0.3}}, 20.0),
        "train": ({"detector": {"metrics": {"recall": 1.0, "median_center_error": 5.9}}}, 30.0),
        "evaluate": ({"labels": {"voxel_P1": {"median": 3.7, "p30": 2.0, "p70": 5.0},
                                 "voxel_P0": {"median": 4.1, "p30": 2.0, "p70": 5.0},
                                 "baseline": {"median": 6.2, "p30": 3.0, "p70": 9.0}},
                      "pipeline": {"rat1_day2 (test)": {"median": 4.4, "missing": 0}}}, 40.0),
        "analyze": ({"stimulated_part": part,
                     "predicted": _analysis("stft_5.47Hz[floor]", part, 0.72, 1),
                     "smoothed": _analysis("stft_5Hz[z]", part, 0.55, 0),
                     "truth": _analysis("stft_5Hz[z]", part, 0.95, 3)}, 50.5),
    }  # fmt: skip
    for step, (results, seconds) in steps.items():
        write_marker(out, preset, step, results, seconds)
    write_summary(out, preset)
    return out


def test_a_finished_demo_is_recorded_with_its_key_figures(bench, finished_demo):
    path = bench.record(finished_demo)
    rec = json.loads(path.read_text())
    assert rec["benchmark"] == "demo" and path.parent.name == "demo"
    assert rec["extra"]["seed"] == 2 and rec["extra"]["preset"] == "tiny"
    assert rec["command"] == ["freipose", "demo", "OUTDIR", "--seed", "2", "--threads", "2",
                              "--preset", "tiny"]  # fmt: skip
    f = rec["figures"]
    assert f["calibration"]["max_center_mm"] == 1.5
    assert f["detector"] == {"recall": 1.0, "median_center_error": 5.9}
    assert f["held_out_jpe_mm"] == {"voxel_P1": 3.7, "voxel_P0": 4.1, "baseline": 6.2}
    assert f["pipeline_jpe_mm"] == {"rat1_day2 (test)": 4.4}
    pred = f["analysis"]["predicted"]
    assert pred["best_variable"] == "stft_5.47Hz[floor]" and pred["best_f1"] == 0.9
    assert pred["paw_share_top5"] == 0.4 and pred["paw_share_top10"] == 0.3
    assert pred["significant"] == 1 and pred["balanced_accuracy"] == 0.72
    assert f["analysis"]["smoothed"]["balanced_accuracy"] == 0.55
    # wall time per step from the step markers, and their sum
    assert f["seconds"] == {"synth": 10.0, "calibrate": 20.0, "train": 30.0, "evaluate": 40.0,
                            "analyze": 50.5, "total": 150.5}  # fmt: skip


def test_an_unfinished_demo_is_refused(bench, finished_demo):
    summary = finished_demo / "summary.json"
    s = json.loads(summary.read_text())
    del s["analysis"]
    summary.write_text(json.dumps(s))
    with pytest.raises(SystemExit, match="has not finished"):
        bench.record(finished_demo)
    with pytest.raises(SystemExit, match="summary.json not found"):
        bench.record(finished_demo / "nothing")


def test_main_records_every_folder_given(bench, finished_demo, monkeypatch, tmp_path):
    monkeypatch.setenv("FREIPOSE_RESULTS_DIR", str(tmp_path / "res"))
    assert bench.main(["--from", str(finished_demo), str(finished_demo)]) == 0
    assert len(list((tmp_path / "res" / "demo").glob("*.json"))) == 2
    with pytest.raises(SystemExit):
        bench.main([])
