"""The world's up direction: stored with the calibration, estimated from labels, used."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.geometry.floor import estimate_up
from freipose.geometry.transforms import rodrigues
from freipose.io.calibration import load_calibration, save_calibration
from freipose.io.calibration_toml import rig_from_toml_text, rig_to_toml_text
from freipose.io.calibration_world import (
    WorldUp,
    WorldUpError,
    resolve_up,
    rig_with_up,
    up_from_labels,
    with_world_up,
    world_up,
)
from freipose.io.labels import LabelSet, SessionInfo, write_labels_h5
from freipose.testing import make_circle_rig

# A world whose up is not z: the rig's frame turned by 70 degrees about x, then shifted.
TURN = rodrigues(np.radians(70.0) * np.array([1.0, 0.0, 0.0]))
SHIFT = np.array([30.0, -200.0, 900.0])
TRUE_UP = TURN @ np.array([0.0, 0.0, 1.0])
FLOOR_POINT = SHIFT + 5.0 * TRUE_UP  # the arena's centre on the floor (paws 5 mm up)


def _walking_animal(frames: int = 200, seed: int = 0) -> np.ndarray:
    """(T, 6, 3) points of an animal walking over the floor, in the turned world (mm)."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 6 * np.pi, frames)[:, None]  # explores the 300 mm arena over time
    path = 140 * np.hstack([np.sin(t) * np.cos(t / 3.1), np.sin(t / 1.7)]) + rng.normal(
        0, 5, (frames, 2)
    )
    heights = np.array([5.0, 5.0, 5.0, 5.0, 40.0, 55.0])  # four paws, back and head
    offs = rng.normal(0, 15, (frames, 6, 2))
    local = np.concatenate(
        [path[:, None] + offs, (heights + rng.normal(0, 1.5, (frames, 6)))[..., None]], -1
    )
    return local @ TURN.T + SHIFT


def _rig_in_turned_world():
    """A circle rig above the floor, moved into the turned world."""
    rig = make_circle_rig(n=4, radius=700.0, height=500.0, size=(320, 240), focal=300.0)
    from freipose.geometry import Camera, CameraRig

    T_inv = TURN.T  # world' -> world: X = TURN.T (X' - SHIFT)
    cams = [
        Camera(c.name, c.size, c.K, c.dist, c.R @ T_inv, c.t - c.R @ T_inv @ SHIFT) for c in rig
    ]
    return CameraRig(tuple(cams))


def test_estimate_up_finds_the_floor_of_a_walking_animal():
    rig = _rig_in_turned_world()
    est = estimate_up(_walking_animal(), rig.centers)
    assert est is not None
    assert np.degrees(np.arccos(est.up @ TRUE_UP)) < 1.0
    assert abs(est.up @ FLOOR_POINT - est.floor) < 3.0
    assert est.cameras_above == 4 and est.flatness < 0.2
    # most cameras decide the side: one camera below the floor does not flip it
    below = np.vstack([rig.centers[:3], [SHIFT - 300 * TRUE_UP]])
    assert estimate_up(_walking_animal(), below).up @ TRUE_UP > 0.99


def test_up_is_stored_in_the_calibration_and_old_files_have_none(tmp_path):
    rig = _rig_in_turned_world()
    assert world_up(rig) is None
    stored = with_world_up(rig, WorldUp(TRUE_UP * 3, "given with --up", 12.5))
    back = world_up(rig_from_toml_text(rig_to_toml_text(stored)))
    assert back is not None and back.source == "given with --up" and back.floor == 12.5
    np.testing.assert_allclose(back.up, TRUE_UP, atol=1e-8)
    save_calibration(stored, tmp_path / "c.toml")
    assert "up_source" in (tmp_path / "c.toml").read_text()
    assert world_up(with_world_up(stored, None)) is None
    with pytest.raises(WorldUpError, match="--up 0,0,1"):
        WorldUp(np.zeros(3), "x")


def test_resolve_up_stored_estimated_or_assumed_with_a_warning(caplog):
    rig = _rig_in_turned_world()
    pts = _walking_animal()
    with caplog.at_level(logging.WARNING):
        got = resolve_up(rig, pts, "the test")
    assert got.up @ TRUE_UP > 0.999 and got.source.startswith("estimated from 1200")
    assert "stores no up direction" in caplog.text and "calib up" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        z = resolve_up(rig, None, "the test")
    np.testing.assert_array_equal(z.up, [0, 0, 1])
    assert "assumes world z is up" in caplog.text
    caplog.clear()
    stored = with_world_up(rig, WorldUp(TRUE_UP, "given"))
    with caplog.at_level(logging.WARNING):
        assert resolve_up(stored, pts).source == "given"
    assert caplog.text == ""
    # points spread alike in every direction fix no plane: refused (the rig keeps no up)
    still = SHIFT + np.random.default_rng(1).normal(0, 20, (50, 6, 3))  # a ball, no plane
    with pytest.raises(WorldUpError, match="do not spread over a plane"):
        up_from_labels(rig, still)
    assert rig_with_up(rig, still) is rig
    assert world_up(rig_with_up(rig, pts)).up @ TRUE_UP > 0.999


def _labels_file(tmp_path, rig, pts):
    n, k = pts.shape[:2]
    labels = LabelSet(
        session=np.array(["s"] * n),
        frame_index=np.arange(n),
        points2d=np.full((n, len(rig), k, 2), np.nan),
        points3d=pts,
        cameras=tuple(rig.names),
        keypoints=tuple(f"kp{i}" for i in range(k)),
        sessions={"s": SessionInfo(calibration=rig)},
    )
    path = tmp_path / "labels.h5"
    write_labels_h5(labels, path)
    return path


def test_calib_up_command_sets_or_estimates_the_up(tmp_path):
    rig = _rig_in_turned_world()
    cal = tmp_path / "calibration.toml"
    save_calibration(rig, cal)
    res = CliRunner().invoke(cli, ["calib", "up", str(cal), "--up", "0, -1, 0", "--floor", "-20"])
    assert res.exit_code == 0, res.output
    got = world_up(load_calibration(cal))
    np.testing.assert_allclose(got.up, [0, -1, 0])
    assert got.floor == -20.0
    labels = _labels_file(tmp_path, rig, _walking_animal())
    out = tmp_path / "estimated.toml"
    res = CliRunner().invoke(
        cli, ["calib", "up", str(cal), "--from-labels", str(labels), "-o", str(out)]
    )
    assert res.exit_code == 0, res.output
    est = world_up(load_calibration(out))
    assert est.up @ TRUE_UP > 0.999 and abs(est.up @ FLOOR_POINT - est.floor) < 3.0
    assert "4 of 4 cameras above" in est.source
    for args, msg in [
        (["--up", "0,0"], "three numbers"),
        (["--up", "0,0,0"], "not all zero"),
        ([], "--from-labels"),
        (["--up", "0,0,1", "--from-labels", str(labels)], "not both"),
    ]:
        res = CliRunner().invoke(cli, ["calib", "up", str(cal), *args])
        assert res.exit_code != 0 and msg in res.output, res.output


def test_grid_rotation_turns_about_the_stored_up():
    from freipose.nn.config import AugmentConfig, config_from_dict
    from freipose.nn.data import prepare_sample
    from freipose.nn.dataset import labeled_sample

    rig = with_world_up(_rig_in_turned_world(), WorldUp(TRUE_UP, "given"))
    pts = _walking_animal(1)[0]
    sample = labeled_sample(rig, [], rig.project(pts), pts)
    cfg = config_from_dict({"model": {"preset": "small", "crop_size": 32}}).model
    aug = AugmentConfig(grid_rotation=180.0)
    rot = prepare_sample(sample, cfg, aug, np.random.default_rng(0))["grid_rotation"]
    np.testing.assert_allclose(rot @ TRUE_UP, TRUE_UP, atol=1e-8)
    assert not np.allclose(rot, np.eye(3))
    plain = with_world_up(rig, None)
    rz = prepare_sample(labeled_sample(plain, [], sample["points2d"], pts), cfg, aug,
                        np.random.default_rng(0))["grid_rotation"]  # fmt: skip
    np.testing.assert_allclose(rz[2], [0, 0, 1])


def test_analysis_world_floor_is_the_calibrations_floor():
    import dataclasses

    from freipose.analysis.io import variables_from_poses
    from freipose.analysis.simulate import simulate_rat

    data = simulate_rat(2.0, fps=50, seed=1)
    assert variables_from_poses(data).floor.offset == 0.0  # no calibration: world origin
    rig = make_circle_rig(n=3, radius=700.0, height=500.0)
    stored = with_world_up(rig, WorldUp(np.array([0.0, 0.0, 1.0]), "the board", 12.0))
    var = variables_from_poses(dataclasses.replace(data, calibration=stored))
    assert var.floor.offset == 12.0 and var.floor.source == "calibration"
