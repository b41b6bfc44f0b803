"""``freipose synth`` end to end through click."""

from __future__ import annotations

import numpy as np
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.io.calibration import load_calibration
from freipose.io.labels import read_labels_h5


def test_synth_command_end_to_end(tmp_path):
    out = tmp_path / "sess"
    runner = CliRunner()
    res = runner.invoke(
        cli, ["synth", str(out), "--frames", "5", "--size", "160x128", "--cameras", "3"]
    )
    assert res.exit_code == 0, res.output
    assert {p.name for p in out.iterdir()} == {
        "cam0.mp4", "cam1.mp4", "cam2.mp4", "true_calibration.toml", "labels.h5", "scene.toml",
    }  # fmt: skip
    labels = read_labels_h5(out / "labels.h5")
    rig = load_calibration(out / "true_calibration.toml")
    assert labels.points2d.shape == (5, 3, 12, 2) and rig.sizes.tolist() == [[160, 128]] * 3
    assert np.abs(rig.project(labels.points3d) - labels.points2d).max() < 0.01

    # reproduce from scene.toml into another folder: same labels
    res = runner.invoke(
        cli, ["synth", str(tmp_path / "again"), "--config", str(out / "scene.toml")]
    )
    assert res.exit_code == 0, res.output
    again = read_labels_h5(tmp_path / "again" / "labels.h5")
    np.testing.assert_array_equal(again.points3d, labels.points3d)

    # a different scene into the same folder is refused with a clear message
    res = runner.invoke(
        cli, ["synth", str(out), "--frames", "5", "--size", "160x128", "--seed", "3"]
    )
    assert res.exit_code == 1 and "--overwrite" in res.output

    # another day of the same animal: --animal-seed is recorded in scene.toml
    res = runner.invoke(
        cli,
        ["synth", str(tmp_path / "day2"), "--frames", "5", "--size", "160x128", "--cameras",
         "3", "--seed", "3", "--animal-seed", "0"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "animal_seed = 0" in (tmp_path / "day2" / "scene.toml").read_text()


def test_synth_command_errors(tmp_path):
    runner = CliRunner()
    bad = tmp_path / "rig.toml"
    bad.write_text('[[camera]]\nname = "a"\nposition = [1, 2, 3]\n')
    res = runner.invoke(cli, ["synth", str(tmp_path / "o"), "--rig", str(bad)])
    assert res.exit_code == 1 and "has no 'look_at'" in res.output
    res = runner.invoke(cli, ["synth", str(tmp_path / "o"), "--size", "big"])
    assert res.exit_code == 2 and "WIDTHxHEIGHT" in res.output
    res = runner.invoke(cli, ["synth", str(tmp_path / "o"), "--stimulation", "body_part=Tail"])
    assert res.exit_code == 1 and "body_part must be one of" in res.output


def test_true_calibration_stores_the_up_and_floor(tmp_path):
    from freipose.io.calibration_world import world_up

    out = tmp_path / "sess"
    res = CliRunner().invoke(
        cli, ["synth", str(out), "--frames", "3", "--size", "96x80", "--cameras", "2"]
    )
    assert res.exit_code == 0, res.output
    up = world_up(load_calibration(out / "true_calibration.toml"))
    assert up is not None and up.floor == 0.0
    np.testing.assert_array_equal(up.up, [0.0, 0.0, 1.0])
    labels = read_labels_h5(out / "labels.h5")
    assert world_up(labels.sessions["sess"].calibration) is not None


def test_missing_sleap_extra_writes_nothing_and_names_the_extra(tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "sleap_io", None)  # import sleap_io: ImportError
    out = tmp_path / "sess"
    res = CliRunner().invoke(
        cli, ["synth", str(out), "--frames", "3", "--size", "96x80", "--label-files", "sleap"]
    )
    assert res.exit_code != 0 and "Traceback" not in res.output
    assert "pip install 'freipose[sleap]'" in res.output
    assert not out.exists() or not any(out.iterdir())
