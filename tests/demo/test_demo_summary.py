"""``OUTDIR/summary.json``: every figure the demo prints, at equal training budgets."""

from __future__ import annotations

import json
import re

import pytest

from freipose.demo.markers import STEPS, write_marker
from freipose.demo.presets import PRESETS
from freipose.demo.summary import build_summary, write_summary


@pytest.mark.slow
def test_summary_holds_the_printed_figures(tiny_demo):
    out, output = tiny_demo
    s = json.loads((out / "summary.json").read_text())
    assert s["preset"] == "tiny" and s["init"] == PRESETS["tiny"].init
    assert set(s["seconds"]) == {*STEPS, "total"}
    assert s["seconds"]["total"] == pytest.approx(sum(s["seconds"][k] for k in STEPS), abs=0.05)
    # equal budgets: the baseline trains as many steps as the voxel network
    steps = PRESETS["tiny"].pose["steps"]
    assert s["budgets"] == {
        "voxel_steps": steps,
        "baseline_steps": steps,
        "detector_steps": PRESETS["tiny"].detector["steps"],
        "views_per_sample": PRESETS["tiny"].n_cameras,
    }
    assert f"triangulation baseline (per-view 2D + robust triangulation), {steps} steps" in output
    printed = dict(re.findall(r"^\s+(\S+)\s+median JPE\s+([\d.]+) mm \(30-70", output, re.M))
    labels = s["evaluation"]["labels"]
    assert set(printed) == set(labels) >= {"voxel_P0", "voxel_P1", "baseline"}
    for name, value in printed.items():
        assert f"{labels[name]['median']:.2f}" == value, name
    centre = re.search(r"largest errors: centre ([\d.]+) mm", output)
    assert centre and f"{s['calibration']['max_center_mm']:.2f}" == centre.group(1)
    assert s["labels"]["train"]["median_3d_vs_truth_mm"] > 0
    assert {"recall", "median_center_error"} <= set(s["detector"])
    for poses in ("predicted", "truth"):
        assert 0 <= s["analysis"][poses]["top10_share_stimulated_part"] <= 1
        assert s["analysis"][poses]["classification"]
    assert s["evaluation"]["pipeline"]


def test_summary_of_a_partial_run_is_strict_json(tmp_path):
    preset = PRESETS["tiny"]
    write_marker(tmp_path, preset, "calibrate", {"summary": {"max_center_mm": 1.5}}, 3.0)
    write_marker(
        tmp_path,
        preset,
        "train",
        {"init": "scratch", "budgets": {"voxel_steps": 6}, "detector": {"metrics": {"recall": 0.5,
         "median_center_error": float("nan")}}},
        4.0,
    )  # fmt: skip
    s = build_summary(tmp_path, preset)
    assert s["calibration"] == {"max_center_mm": 1.5} and "evaluation" not in s
    assert s["detector"] == {"recall": 0.5, "median_center_error": None}
    assert s["seconds"] == {"calibrate": 3.0, "train": 4.0, "total": 7.0}
    text = write_summary(tmp_path, preset).read_text()
    assert "NaN" not in text and json.loads(text)["init"] == "scratch"
