"""``freipose demo --preset tiny`` end to end: every output exists and is valid; rerun skips."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.demo.markers import STEPS
from freipose.demo.presets import PRESETS, STIM_PART
from freipose.demo.steps.analyze import study_toml
from freipose.geometry.alignment import align_similarity

# tiny_demo: the shared tiny demo run (tests/demo/conftest.py)


def test_stimulated_part_errors_split_frames_as_the_analysis_does():
    from freipose.demo.steps.evaluate import stimulated_part_errors

    times = np.arange(100) / 10.0  # 10 s at 10 fps
    truth = np.zeros((100, 3))
    inside = (times >= 2.0) & (times < 4.0)
    truth[inside, 2] = 20.0  # lifted 20 mm during the window 2-4 s
    pred = truth.copy()
    pred[inside, 2] = 12.0  # the prediction lifts it 12 mm: 8 mm too low
    pred[~inside, 0] = 3.0  # and 3 mm off sideways elsewhere
    pred[0] = np.nan
    r = stimulated_part_errors(pred, truth, times, np.array([[2.0, 4.0]]), 0.5, 1.0)
    # stimulated: 2.5-4.0 s (frames 25-39 and 40: the end is included, and it is not lifted)
    assert r["stimulated"]["n"] == 16
    assert r["stimulated"]["median_error_mm"] == pytest.approx(8.0)
    assert r["stimulated"]["median_height_error_mm"] == pytest.approx(-8.0)
    # rest: further than 1 s from the window, frame 0 missing
    assert r["rest"]["n"] == 100 - 41 - 1  # frames 10-50 are near the window
    assert r["rest"]["median_error_mm"] == pytest.approx(3.0)
    assert r["rest"]["median_height_error_mm"] == pytest.approx(0.0)
    assert r["lift_true_mm"] == pytest.approx(20.0 * 15 / 16)
    assert r["lift_pred_mm"] == pytest.approx(12.0 * 15 / 16)


@pytest.mark.slow
def test_tiny_demo_outputs(tiny_demo):
    from freipose.analysis.study import load_study
    from freipose.io.calibration import load_calibration
    from freipose.io.labels import read_labels_h5
    from freipose.io.poses import read_poses_h5

    out, output = tiny_demo
    p = PRESETS["tiny"]
    for i, step in enumerate(STEPS, start=1):
        assert f"[{i}/{len(STEPS)}]" in output
        marker = json.loads((out / ".demo" / f"{step}.done").read_text())
        assert marker["preset"]["name"] == "tiny"
    # 1 synth: sessions with 7 cameras, events, board videos
    for s in p.sessions:
        folder = out / "recordings" / s.name
        assert len(list(folder.glob("cam*.mp4"))) == 7
        assert (folder / "events.csv").read_text().startswith("start_s,end_s")
    # 2 calibration: a valid file, finite and plausible errors against the truth
    rig = load_calibration(out / "calibration" / "calibration.toml")
    assert len(rig) == 7
    comp = json.loads((out / "calibration" / "comparison.json").read_text())
    for key in ("center_mm", "rotation_deg"):
        v = np.asarray(comp[key])
        assert v.shape == (7,) and np.isfinite(v).all()
    assert max(comp["center_mm"]) < 30.0
    assert max(comp["rotation_deg"]) < 5.0
    assert np.abs(comp["focal_percent"]).max() < 5.0
    assert "centre error" in output
    # 3 labels
    lab = read_labels_h5(out / "labels" / "train.h5")
    assert len(lab) == p.label_instants
    assert np.isfinite(lab.points3d).all(-1).mean() > 0.7
    assert lab.rig_for(p.sessions[0].name).allclose(rig)
    ev = read_labels_h5(out / "labels" / "eval.h5")
    assert len(ev) == p.eval_instants and np.isfinite(ev.points3d).all()
    # 4 training: detector, voxel network, baseline
    for f in ("detector/detector.pt", "pose/model.pt", "baseline/model.pt", "pose/log.png"):
        assert (out / "train" / f).is_file(), f
    # 5 predict: readable poses for every analysed session, covering every frame; the
    # labeling session is not predicted
    assert [s.split for s in p.sessions] == ["label", "test", "train"]
    assert not (out / "poses" / f"{p.sessions[0].name}.poses.h5").exists()
    for s in p.analysed:
        data = read_poses_h5(out / "poses" / f"{s.name}.poses.h5")
        assert data.poses.shape == (p.session_frames, 12, 3)
        assert np.isfinite(data.poses).all(-1).any(-1).mean() > 0.5
        assert data.calibration is not None and data.calibration.allclose(rig)
    assert list((out / "overlay").glob("*.png"))
    clip = next((out / "overlay").glob("*.mp4")).read_bytes()
    assert b"avcC" in clip and clip.find(b"moov") < clip.find(b"mdat")  # H.264, index first
    from freipose.io.video import FrameSource

    assert FrameSource(next((out / "overlay").glob("*.mp4"))).width == 3 * p.size[0]
    # 6 evaluation: voxel and baseline JPE, finite
    metrics = json.loads((out / "evaluation" / "labels" / "metrics.json").read_text())
    assert set(metrics) == {"voxel_P0", "voxel_P1", "baseline", "references", "comparisons"}
    ends = {(c["a"], c["b"]) for c in metrics["comparisons"]}
    assert {("voxel_P1", "baseline"), ("voxel_P0", "baseline")} <= ends
    assert all(np.isfinite(metrics[m]["overall"]["median"]) for m in ("voxel_P0", "baseline"))
    assert (out / "evaluation" / "pipeline" / "jpe_boxplot.png").is_file()
    pipeline = json.loads((out / ".demo" / "evaluate.done").read_text())["results"]["pipeline"]
    for s in p.analysed:
        stim = pipeline[f"{s.name} ({s.split})"]["stimulated_part"]
        assert stim["stimulated"]["n"] > 0 and stim["rest"]["n"] > 0
        assert np.isfinite(stim["lift_true_mm"]) and stim["stimulated"]["median_error_mm"] >= 0
    assert f"{STIM_PART} in the stimulated frames vs the rest" in output
    # 7 analysis: a valid study and its tables and figures
    study = load_study(out / "analysis" / "study.toml")
    assert {r.split for r in study.recordings} == {"train", "test"}
    assert [r.name for r in study.recordings] == [s.name for s in p.analysed]
    for sub in ("results", "results_truth", "results_smoothed"):  # + truth, smoothed poses
        res = out / "analysis" / sub
        for f in ("classification.csv", "attribution.csv", "classifier_response.png"):
            assert (res / f).is_file(), f
        assert list(res.glob("attribution_*.png"))
    marker = json.loads((out / ".demo" / "analyze.done").read_text())["results"]
    assert 0 <= marker["truth"]["top10_share_stimulated_part"] <= 1
    assert Path(marker["smooth"]["figure"]).is_file()  # raw vs smoothed trajectories
    assert set(marker["smooth"]["balanced_accuracy"]) == {"raw", "smoothed"}
    # 8 report: every referenced figure and link exists
    html = (out / "report.html").read_text()
    refs = re.findall(r'(?:src|href)="([^"#][^"]*)"', html)
    assert len(refs) >= 12
    for ref in refs:
        assert (out / ref).is_file(), ref
    assert "Figure not written" not in html and "Video not written" not in html
    # the raw vs smoothed figures the terminal prints are the report's table rows
    text = re.sub(r"\s+", " ", re.sub(r"<[^>]+>", " ", html))
    printed = output.split("raw vs smoothed:\n")[1].split("\n")[:4]
    for line in printed:
        name, values = line.strip().split(": ", 1)
        raw, smoothed = values.split(" vs ")
        assert f"{name} {raw} {smoothed}" in text, line
    assert 'src="analysis/smoothed_vs_raw.png"' in html
    assert "The clip runs from " in text
    for fig in ("comparison.png", "log.png", "jpe_boxplot.png", "attribution_", "classifier"):
        assert fig in html


@pytest.mark.slow
def test_tiny_demo_rerun_skips_and_refuses_other_preset(tiny_demo):
    out, _ = tiny_demo
    res = CliRunner().invoke(cli, ["demo", str(out), "--preset", "tiny"])
    assert res.exit_code == 0, res.output
    assert res.output.count("skipped") == len(STEPS) - 1  # the report is always rewritten
    res = CliRunner().invoke(cli, ["demo", str(out)])  # default preset: small
    assert res.exit_code != 0
    assert "other settings" in res.output and "another output folder" in res.output


def test_align_similarity_recovers_transform(rng):
    from freipose.geometry.transforms import rodrigues_to_matrix

    A = rng.normal(size=(7, 3)) * 500
    R = rodrigues_to_matrix(np.array([0.3, -0.2, 1.1]))
    B = 1.01 * A @ R.T + np.array([10.0, -20.0, 5.0])
    s, R2, t = align_similarity(A, B)
    assert s == pytest.approx(1.01)
    np.testing.assert_allclose(R2, R, atol=1e-9)
    np.testing.assert_allclose(t, [10.0, -20.0, 5.0], atol=1e-6)


def test_study_manifest_is_valid(tmp_path):
    from freipose.analysis.study import load_study
    from freipose.demo.context import DemoContext

    ctx = DemoContext(tmp_path, PRESETS["small"])
    path = tmp_path / "analysis" / "study.toml"
    path.parent.mkdir()
    path.write_text(study_toml(ctx, path.parent))
    study = load_study(path, check_files=False)
    assert [(r.name, r.split) for r in study.recordings] == [
        ("rat1_day2", "test"),
        ("rat1_day3", "train"),
    ]  # the labeling day (rat1_day1) is not analysed
    poses = study.recordings[0].poses.resolve()
    assert poses == (tmp_path / "poses" / "rat1_day2.poses.h5").resolve()


def test_unknown_preset_is_a_clear_error(tmp_path):
    from freipose.demo.runner import run_demo

    with pytest.raises(ValueError, match="unknown demo preset"):
        run_demo(tmp_path / "x", "huge")


def test_small_preset_training_config_is_valid_and_trains_on_view_subsets(tmp_path):
    from freipose.demo.context import DemoContext
    from freipose.demo.steps.train import _train_config
    from freipose.io.toml import read_toml
    from freipose.nn.config import config_from_dict

    path = _train_config(DemoContext(tmp_path, PRESETS["small"]))
    cfg = config_from_dict(read_toml(path, "training config"))
    assert cfg.augment.max_views == 4 < PRESETS["small"].n_cameras
    assert cfg.schedule.steps == PRESETS["small"].pose["steps"]
    assert cfg.schedule.refine_start == 0.0 and cfg.model.init == "base"
    # fine-tuning the bases: a short phase at the high rate, most steps after its drop
    sched = cfg.schedule
    assert sched.lr_at(sched.lr_decay_steps - 1) == sched.lr > sched.lr_at(sched.lr_decay_steps)
    assert sched.lr_decay_steps <= sched.steps // 2
