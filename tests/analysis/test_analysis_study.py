"""End-to-end attribution on synthetic recordings, frame labelling and bad study inputs."""

from __future__ import annotations

import h5py
import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from freipose.analysis.io import cached_variables
from freipose.analysis.simulate import simulate_rat, simulate_study, write_events_csv
from freipose.analysis.stats import effective_frames
from freipose.analysis.study import (
    IGNORED,
    NOT_STIMULATED,
    STIMULATED,
    StudyError,
    label_frames,
    load_study,
    read_events,
    recording_entry,
)
from freipose.cli.main import cli
from freipose.io.poses import PoseData, write_poses_h5

STIM_KP = "Paw Front Right"


@pytest.fixture(scope="module")
def study_result(tmp_path_factory):
    """A two-animal study (120 s at 40 fps, ~19 stimulations per recording) analysed by the
    CLI; the right front paw is lifted and oscillates at 10 Hz during stimulation."""
    folder = tmp_path_factory.mktemp("study")
    path = simulate_study(
        folder,
        ("rat1", "rat2"),
        "10Hz",
        duration_s=120.0,
        fps=40.0,
        period_s=6.0,
        length_s=2.0,
        seed=7,
    )
    out = folder / "out"
    res = CliRunner().invoke(
        cli,
        [
            "analyze",
            str(path),
            "-o",
            str(out),
            "--onset-delay",
            "0.2",
            "--margin",
            "1",
            "--pre",
            "2",
            "--post",
            "2",
            "-j",
            "2",
        ],
    )
    assert res.exit_code == 0, res.output
    return out, res.output


@pytest.mark.slow
def test_attribution_finds_the_stimulated_keypoint(study_result):
    out, _ = study_result
    att = pd.read_csv(out / "attribution.csv")
    assert list(att.columns[:9]) == [
        "animal",
        "condition",
        "rank",
        "variable",
        "keypoints",
        "f1",
        "p_value",
        "p_adjusted",
        "significant",
    ]
    for _animal, g in att.groupby("animal"):
        g = g.sort_values("rank")
        assert len(g) == 912
        top = g.head(10)
        assert top["keypoints"].str.contains(STIM_KP).all(), top
        assert top["significant"].all(), top
        sig = g[g["significant"]]
        # Every significant variable involves the stimulated paw; no unrelated keypoint does.
        assert sig["keypoints"].str.contains(STIM_KP).all(), sig
        assert len(sig) >= 5
        unrelated = g[~g["keypoints"].str.contains(STIM_KP)]
        assert unrelated["f1"].max() < 0.8
        assert np.allclose(g["p_adjusted"], np.minimum(1, g["p_value"] * 912), rtol=1e-4)


@pytest.mark.slow
def test_full_classifier_generalizes_and_outputs_exist(study_result):
    out, output = study_result
    cls = pd.read_csv(out / "classification.csv")
    assert set(zip(cls["animal"], cls["evaluated_on"])) == {
        ("rat1", "rat1"),
        ("rat1", "rat2"),
        ("rat2", "rat2"),
        ("rat2", "rat1"),
    }
    assert (cls["balanced_accuracy"] > 0.8).all() and (cls["f1"] > 0.8).all()
    assert (cls["p_value"] < 1e-3).all()
    dyn = pd.read_csv(out / "dynamics.csv")
    for col in ("animal", "condition", "evaluated_on", "time_s", "mean_prediction"):
        assert col in dyn.columns
    g = dyn[(dyn["animal"] == "rat1") & (dyn["evaluated_on"] == "rat1")]
    inside = g[(g["time_s"] > 0.5) & (g["time_s"] < 1.9)]["mean_prediction"].mean()
    before = g[(g["time_s"] < -1.2)]["mean_prediction"].mean()
    assert inside > 0.8 and before < 0.3
    for name in (
        "attribution_rat1_10Hz.png",
        "attribution_rat2_10Hz.png",
        "classifier_response.png",
        "top_variables_rat1_10Hz.png",
    ):
        assert (out / name).stat().st_size > 10_000
    assert len(list((out / "variables").glob("*.vars.h5"))) == 4


@pytest.mark.slow
def test_rerun_reuses_cached_variables(study_result):
    out, _ = study_result
    cache = out / "variables" / "rat1_test.vars.h5"
    stamp = cache.stat().st_mtime_ns
    var = cached_variables(out.parent / "rat1_test.poses.h5", cache)
    assert cache.stat().st_mtime_ns == stamp and var.values.shape == (4800, 912)
    # Other settings: recomputed and rewritten.
    var = cached_variables(out.parent / "rat1_test.poses.h5", cache, floor="auto")
    assert cache.stat().st_mtime_ns != stamp and var.floor.source == "auto"


def test_label_frames_delay_and_margin():
    t = np.arange(0, 20, 0.5)
    lab = label_frames(t, np.array([[5.0, 8.0]]), onset_delay_s=1.0, margin_s=2.0)
    assert lab[t == 4.5] == IGNORED and lab[t == 5.5] == IGNORED
    assert lab[t == 6.0] == STIMULATED and lab[t == 8.0] == STIMULATED
    assert lab[t == 9.5] == IGNORED and lab[t == 10.5] == NOT_STIMULATED
    assert lab[t == 2.5] == NOT_STIMULATED and lab[t == 3.0] == IGNORED


def test_effective_frames_counts_blocks_not_frames():
    rng = np.random.default_rng(0)
    y = np.repeat(rng.integers(0, 2, 40), 50)  # 40 blocks of 50 frames
    p = np.repeat(rng.integers(0, 2, 40), 50)  # an unrelated blocky prediction
    n_eff = effective_frames(y, p, np.array([len(y)]))
    assert 10 < n_eff < 400  # far fewer than the 2000 frames
    white = rng.integers(0, 2, 2000)
    assert effective_frames(y, white, np.array([2000])) > 1000


def _mini_study(tmp_path, events="start_s,end_s\n2,4\n", test=True, up=True, keypoints=None):
    data = simulate_rat(10.0, fps=20, seed=0)
    if keypoints is not None:
        data = PoseData(data.poses, data.confidence, keypoints, data.frame_index, data.fps)
    write_poses_h5(data, tmp_path / "a.poses.h5")
    if not up:
        with h5py.File(tmp_path / "a.poses.h5", "a") as f:
            del f.attrs["up"]
    (tmp_path / "a_events.csv").write_text(events)
    recs = [("a_train", "train")] + ([("a_test", "test")] if test else [])
    text = "".join(
        f'[[recordings]]\nname = "{n}"\nposes = "a.poses.h5"\nevents = "a_events.csv"\n'
        f'animal = "rat1"\ncondition = "10Hz"\nsplit = "{s}"\n\n'
        for n, s in recs
    )
    (tmp_path / "study.toml").write_text(text)
    return tmp_path / "study.toml"


def _run(study, tmp_path):
    return CliRunner().invoke(cli, ["analyze", str(study), "-o", str(tmp_path / "out")])


def test_events_outside_recording_is_an_error(tmp_path):
    res = _run(_mini_study(tmp_path, "start_s,end_s\n8,12\n"), tmp_path)
    assert res.exit_code != 0 and "outside the recording" in res.output
    assert "Traceback" not in res.output


def test_overlapping_windows_are_an_error(tmp_path):
    path = tmp_path / "e.csv"
    path.write_text("start_s,end_s\n1,3\n2.5,4\n")
    with pytest.raises(StudyError, match="overlap"):
        read_events(path)
    path.write_text("start,stop\n1,3\n")
    with pytest.raises(StudyError, match="start_s,end_s"):
        read_events(path)
    write_events_csv(np.array([[1.0, 2.0]]), path)
    assert np.allclose(read_events(path), [[1, 2]])
    res = _run(_mini_study(tmp_path, "start_s,end_s\n1,3\n2.5,4\n"), tmp_path)
    assert res.exit_code != 0 and "overlap" in res.output


def test_group_without_test_recording_is_an_error(tmp_path):
    with pytest.raises(StudyError, match=r"has no test recording"):
        load_study(_mini_study(tmp_path, test=False))


def test_poses_without_up_is_an_error(tmp_path):
    res = _run(_mini_study(tmp_path, up=False), tmp_path)
    assert res.exit_code != 0 and "'up' attribute" in res.output


def test_poses_with_other_keypoints_is_an_error(tmp_path):
    study = _mini_study(tmp_path, keypoints=tuple(f"kp{i}" for i in range(12)))
    res = _run(study, tmp_path)
    assert res.exit_code != 0 and "do not match skeleton 'rat'" in res.output


def test_variables_and_floor_commands(tmp_path):
    data = simulate_rat(5.0, fps=50, seed=2)
    write_poses_h5(data, tmp_path / "p.poses.h5")
    r = CliRunner().invoke(
        cli, ["analyze", "floor", str(tmp_path / "p.poses.h5"), "-o", str(tmp_path / "floor.toml")]
    )
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(
        cli,
        [
            "analyze",
            "variables",
            str(tmp_path / "p.poses.h5"),
            "-o",
            str(tmp_path / "v.vars.h5"),
            "--floor",
            str(tmp_path / "floor.toml"),
        ],
    )
    assert r.exit_code == 0, r.output
    assert "912 variables x 250 frames" in r.output
    with h5py.File(tmp_path / "v.vars.h5") as f:
        assert f["values"].shape == (250, 912)
        assert f.attrs["floor_source"].endswith("floor.toml")
    r = CliRunner().invoke(
        cli,
        [
            "analyze",
            "variables",
            str(tmp_path / "p.poses.h5"),
            "-o",
            str(tmp_path / "w.vars.h5"),
            "--floor",
            "nofile.toml",
        ],
    )
    assert r.exit_code != 0 and "'world', 'auto' or an existing floor TOML" in r.output
    r = CliRunner().invoke(cli, ["analyze", "--help"])
    assert r.exit_code == 0 and "variables" in r.output
    r = CliRunner().invoke(cli, ["analyze", "run", "--help"])
    assert "default: 0.4" in r.output and "default: 1.5" in r.output


def test_recording_entry_reads_back_with_quotes_and_backslashes(tmp_path):
    entries = [
        recording_entry('rat "A"', "a.poses.h5", "a.csv", "rat A", "10\\Hz", "train"),
        recording_entry("rat_b", "b.poses.h5", "b.csv", "rat A", "10\\Hz", "test"),
    ]
    path = tmp_path / "study.toml"
    path.write_text('skeleton = "rat"\n\n' + "\n".join(entries), encoding="utf-8")
    study = load_study(path, check_files=False)
    first = study.recordings[0]
    assert (first.name, first.animal, first.split) == ('rat "A"', "rat A", "train")
    assert first.condition == "10\\Hz" and first.poses.name == "a.poses.h5"
    assert study.recordings[1].split == "test"
