"""Bad input to ``freipose analyze``: keypoints missing throughout a recording, bad events."""

from __future__ import annotations

import h5py
import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from freipose.analysis import io as analysis_io
from freipose.analysis.simulate import simulate_study
from freipose.analysis.single import fit_block
from freipose.analysis.stats import scores
from freipose.cli.main import cli

FRONT_PAW = "Paw Front Right"


def _study(folder):
    """One animal, a 40 s train and a 40 s test recording at 20 fps (6 windows each)."""
    return simulate_study(
        folder, ("rat1",), "10Hz", duration_s=40.0, fps=20.0, period_s=6.0, length_s=2.0, seed=1
    )


def _blank(poses, keypoints, frames=slice(None)):
    """Set keypoints of a poses file to NaN in the given frames."""
    with h5py.File(poses, "a") as f:
        names = [k.decode() if isinstance(k, bytes) else str(k) for k in f["keypoints"][()]]
        x = f["poses"][()]
        for kp in keypoints:
            x[frames, names.index(kp)] = np.nan
        f["poses"][...] = x


def _analyze(study, out, *extra):
    args = ["analyze", str(study), "-o", str(out), "--no-figures", *extra]
    return CliRunner().invoke(cli, args)


# ------------------------------------------------------------ keypoints missing throughout


def test_keypoint_missing_throughout_a_recording_is_dropped_with_a_warning(tmp_path):
    study = _study(tmp_path)
    _blank(tmp_path / "rat1_test.poses.h5", [FRONT_PAW])
    res = _analyze(study, tmp_path / "out")
    assert res.exit_code == 0, res.output
    assert "WARNING" in res.output
    warning = next(line for line in res.output.splitlines() if "missing (NaN)" in line)
    assert f"'{FRONT_PAW}'" in warning and "'rat1_test'" in warning
    assert "left out of the whole analysis" in warning
    cls = pd.read_csv(tmp_path / "out" / "classification.csv")
    assert (cls["n_frames"] > 0).all() and cls["p_value"].notna().all()
    att = pd.read_csv(tmp_path / "out" / "attribution.csv")
    assert (att["n_frames"] > 0).all()
    assert not att["keypoints"].str.contains(FRONT_PAW).any()
    assert cls["n_variables_used"].iloc[0] == len(att) < 912


def test_recording_without_any_defined_variable_is_an_error(tmp_path):
    study = _study(tmp_path)
    with h5py.File(tmp_path / "rat1_test.poses.h5") as f:
        keypoints = [k.decode() if isinstance(k, bytes) else str(k) for k in f["keypoints"][()]]
    _blank(tmp_path / "rat1_test.poses.h5", keypoints)
    res = _analyze(study, tmp_path / "out")
    assert res.exit_code == 1, res.output
    assert "Traceback" not in res.output
    assert "no variable left to analyze" in res.output
    assert "recording 'rat1_test'" in res.output and f"'{FRONT_PAW}'" in res.output
    assert "check the predictions" in res.output and "remove them from the study file" in res.output
    assert not (tmp_path / "out" / "classification.csv").exists()


def test_recording_without_a_usable_frame_is_an_error(tmp_path):
    """Nose missing in the first half and Tail in the second: every variable is defined
    somewhere, but no frame has them all."""
    study = _study(tmp_path)
    _blank(tmp_path / "rat1_test.poses.h5", ["Nose"], slice(0, 400))
    _blank(tmp_path / "rat1_test.poses.h5", ["Tail"], slice(400, None))
    res = _analyze(study, tmp_path / "out")
    assert res.exit_code == 1, res.output
    assert "no usable frames: recording 'rat1_test'" in res.output
    assert "remove them from the study file" in res.output
    assert not (tmp_path / "out" / "classification.csv").exists()


def test_no_p_value_on_zero_frames():
    ba, f1, p_naive, n_eff, p = scores(np.zeros(0), np.zeros(0))
    assert np.isnan([ba, f1, p_naive, p]).all() and n_eff == 0
    xtr = np.random.default_rng(0).normal(size=(40, 1))
    ytr = np.repeat([0, 1], 20)
    xte = np.full((10, 1), np.nan)
    ((f1, p, ba, n, n_eff, p_naive),) = fit_block(
        xtr, ytr, xte, np.repeat([0, 1], 5), np.zeros(10, dtype=np.int64), 0.0025, 1000
    )
    assert n == 0 and np.isnan([f1, p, ba, p_naive]).all()


# ------------------------------------------------------------------------- events files


@pytest.fixture
def no_variables(monkeypatch):
    """Fail the test if any variable is computed."""

    def forbidden(*args, **kwargs):
        raise AssertionError("compute_variables was called before the events were checked")

    monkeypatch.setattr(analysis_io, "compute_variables", forbidden)


BAD_EVENTS = [
    ("start,stop\n1,3\n", ["line 1", "start_s,end_s", "add or correct the header"]),
    ("start_s,end_s\n1,3\n5,abc\n", ["line 3", "must be numbers", "correct or remove"]),
    ("start_s,end_s\n1,3\n5,nan\n", ["line 3", "finite", "correct or remove"]),
    ("start_s,end_s\n1,3\n9,7\n", ["line 3", "ends (7.0 s) before it starts", "greater"]),
    ("start_s,end_s\n1,3\n\n20,30\n2.5,4\n", ["lines 2 and 5", "overlap", "merge or correct"]),
    ("start_s,end_s\n1,3\n38,41\n", ["line 3", "outside the recording", "0 to 40.000 s"]),
    ("start_s,end_s\n-1,3\n", ["line 2", "outside the recording", "correct or remove"]),
    (b"start_s,end_s\n1,3\xff\xfe\n", ["not a readable CSV text file", "start_s,end_s"]),
]


@pytest.mark.parametrize(("content", "expected"), BAD_EVENTS)
def test_bad_events_file_fails_before_any_variable_is_computed(
    tmp_path, no_variables, content, expected
):
    study = _study(tmp_path)
    events = tmp_path / "rat1_test_events.csv"
    if isinstance(content, bytes):
        events.write_bytes(content)
    else:
        events.write_text(content)
    res = _analyze(study, tmp_path / "out")
    assert res.exit_code == 1, res.output
    assert "compute_variables was called" not in str(res.exception), res.output
    assert "Traceback" not in res.output
    assert f"events file {events}" in res.output
    for text in expected:
        assert text in res.output, res.output
    assert not list((tmp_path / "out").glob("variables/*.vars.h5"))


def test_every_bad_events_file_is_reported(tmp_path, no_variables):
    study = _study(tmp_path)
    (tmp_path / "rat1_train_events.csv").write_text("start_s,end_s\n3,1\n")
    (tmp_path / "rat1_test_events.csv").write_text("start_s,end_s\n50,52\n")
    res = _analyze(study, tmp_path / "out")
    assert res.exit_code == 1, res.output
    assert "2 events problems in study" in res.output
    assert "rat1_train_events.csv, line 2" in res.output
    assert "rat1_test_events.csv (rat1_test), line 2" in res.output


# ------------------------------------------------------------------ incomplete poses files


def _make_incomplete(poses, done):
    """Mark a poses file as an unfinished prediction run with ``done`` frames predicted."""
    with h5py.File(poses, "a") as f:
        x = f["poses"][()]
        x[done:] = np.nan
        f["poses"][...] = x
        f.attrs["complete"] = False
        f.attrs["completed_frames"] = done


def test_incomplete_poses_file_in_a_study_is_refused_unless_allowed(tmp_path):
    study = _study(tmp_path)
    poses = tmp_path / "rat1_test.poses.h5"
    _make_incomplete(poses, 600)
    res = _analyze(study, tmp_path / "out")
    assert res.exit_code == 1, res.output
    assert f"{poses} is incomplete (600 of 800 frames predicted)" in res.output
    assert "--allow-incomplete" in res.output and "Traceback" not in res.output
    assert not list((tmp_path / "out").glob("variables/*.vars.h5"))
    res = _analyze(study, tmp_path / "out", "--allow-incomplete")
    assert res.exit_code == 0, res.output
    assert f"{poses} (rat1_test) is incomplete: 200 frames have no prediction" in res.output
    assert (tmp_path / "out" / "classification.csv").is_file()


def test_partial_poses_file_in_a_study_is_refused(tmp_path):
    study = _study(tmp_path)
    partial = tmp_path / "rat1_test.poses.h5.partial"
    (tmp_path / "rat1_test.poses.h5").rename(partial)
    study.write_text(study.read_text().replace('"rat1_test.poses.h5"', f'"{partial.name}"'))
    res = _analyze(study, tmp_path / "out")
    assert res.exit_code == 1, res.output
    assert f"{partial} is incomplete" in res.output and "--allow-incomplete" in res.output


def test_variables_and_floor_refuse_an_incomplete_poses_file_unless_allowed(tmp_path):
    _study(tmp_path)
    poses = tmp_path / "rat1_test.poses.h5"
    _make_incomplete(poses, 600)
    for cmd in (
        ["variables", str(poses), "-o", str(tmp_path / "v.vars.h5")],
        ["floor", str(poses), "-o", str(tmp_path / "floor.toml")],
    ):
        res = CliRunner().invoke(cli, ["analyze", *cmd])
        assert res.exit_code == 1, res.output
        assert "is incomplete (600 of 800 frames predicted)" in res.output
        res = CliRunner().invoke(cli, ["analyze", *cmd, "--allow-incomplete"])
        assert res.exit_code == 0, res.output
        assert "200 frames have no prediction" in res.output


def test_test_recording_without_stimulation_gets_no_balanced_accuracy(tmp_path):
    study = _study(tmp_path)
    (tmp_path / "rat1_test_events.csv").write_text("start_s,end_s\n")  # no window
    res = _analyze(study, tmp_path / "out")
    assert res.exit_code == 1 and "Traceback" not in res.output
    assert "needs test frames of both classes" in res.output
    assert "0 stimulated and" in res.output and "'rat1_test'" in res.output
    assert "rat1_test_events.csv" in res.output
    assert not (tmp_path / "out" / "classification.csv").exists()
