"""Geometry of the behavioral variables on hand-made poses; floor fit; VARS.h5 round trip."""

from __future__ import annotations

import numpy as np
import pytest

from freipose.analysis.floor import FloorError, FloorPlane, fit_floor, load_floor, save_floor
from freipose.analysis.io import read_variables_h5, variables_from_poses, write_variables_h5
from freipose.analysis.signals import interpolate_gaps, stft_amplitude
from freipose.analysis.simulate import RAT_REST_POSE, simulate_rat
from freipose.analysis.variables import VariableConfig, VariablesError, compute_variables
from freipose.io.poses import PoseData
from freipose.skeleton import load_skeleton

RAT = load_skeleton("rat")


def level_rat(t: int = 200, height: float = 50.0) -> np.ndarray:
    """(T, 12, 3) a static rat facing +x whose ears, tail and nose are all at ``height``."""
    pose = np.array([RAT_REST_POSE[k] for k in RAT.keypoints], dtype=float)
    for name in ("Ear Right", "Ear Left", "Tail", "Nose"):
        pose[RAT.index(name), 2] = height
    return np.broadcast_to(pose, (t, 12, 3)).copy()


def compute(poses: np.ndarray, fps: float = 100.0, floor: FloorPlane | None = None, **kw):
    floor = floor or FloorPlane.world([0, 0, 1])
    return compute_variables(poses, np.arange(len(poses)), fps, RAT, floor, VariableConfig(**kw))


def test_rat_has_912_named_variables():
    var = compute(level_rat())
    assert var.values.shape == (200, 912)
    assert var.values.dtype == np.float32
    assert len(var.frequencies) == 33
    assert "local_z[Paw Front Right]" in var.names
    assert "floor_dist_stft_9.38Hz[Nose]" in var.names
    assert "angle[head_pitch]" in var.names and "angle_vel[paw_left]" in var.names
    i = var.names.index("angle[paw_right]")
    assert set(var.involved_names(i)) == {"Tail", "Ear Right", "Ear Left", "Paw Front Right"}
    j = var.names.index("origin_dist_stft_0Hz[Nose]")
    assert var.involved_names(j) == ["Nose"]
    counts = {k: var.kinds.count(k) for k in set(var.kinds)}
    assert counts == {
        "local": 36,
        "local_vel": 36,
        "origin_dist": 12,
        "origin_dist_vel": 12,
        "origin_dist_stft": 396,
        "floor_dist": 12,
        "floor_dist_stft": 396,
        "angle": 6,
        "angle_vel": 6,
    }


def test_level_rat_angles_and_body_frame():
    var = compute(level_rat())
    assert np.allclose(var.column("angle[body_elevation]"), 0, atol=1e-4)
    assert np.allclose(var.column("angle[head_elevation]"), 0, atol=1e-4)
    assert np.allclose(var.column("angle[head_roll]"), 0, atol=1e-4)
    assert np.allclose(var.column("angle[head_pitch]"), 0, atol=1e-4)  # head in line with body
    assert np.allclose(var.column("angle_vel[body_elevation]"), 0, atol=1e-4)
    # Body frame: origin between the ears, y towards the tail, x to the left, z up.
    assert np.allclose(var.column("local_y[Tail]"), 150, atol=1e-3)
    assert np.allclose(var.column("local_x[Tail]"), 0, atol=1e-3)
    assert np.allclose(var.column("local_x[Ear Left]"), 17, atol=1e-3)
    assert np.allclose(var.column("local_y[Nose]"), -42, atol=1e-3)
    assert np.allclose(var.column("floor_dist[Nose]"), 50, atol=1e-3)
    assert np.allclose(var.column("local_vel_x[Nose]"), 0, atol=1e-3)


def test_rearing_rat_has_positive_body_elevation():
    poses = level_rat()
    tail = RAT.index("Tail")
    poses[:, tail, 2] = 50 - 150 * np.tan(np.radians(20))  # ears 20 deg above the tail
    var = compute(poses)
    assert np.allclose(var.column("angle[body_elevation]"), 20, atol=1e-3)
    # Tilting the body relative to a level head makes the head pitch 20 deg.
    assert np.allclose(var.column("angle[head_pitch]"), 20, atol=1e-3)


def test_rotation_about_up_leaves_local_variables_unchanged():
    data = simulate_rat(4.0, fps=100, seed=3)
    a = np.radians(73)
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    shift = np.array([250.0, -80.0, 0.0])
    v1 = compute(data.poses.astype(float))
    v2 = compute(data.poses.astype(float) @ rot.T + shift)
    assert np.allclose(v1.values, v2.values, atol=2e-3, rtol=1e-4)


def test_ten_hz_oscillation_peaks_in_matching_stft_bin():
    fps = 100.0
    poses = level_rat(1000)
    paw = RAT.index("Paw Front Right")
    t = np.arange(1000) / fps
    poses[:, paw, 2] += 5.0 * np.sin(2 * np.pi * 10.0 * t)
    var = compute(poses, fps=fps)
    cols = [
        var.names.index(f"floor_dist_stft_{lab}[Paw Front Right]")
        for lab in [f"{f:.3g}Hz" for f in var.frequencies]
    ]
    spec = var.values[500, cols]
    k = int(np.argmax(spec[1:])) + 1
    assert k == int(np.argmin(np.abs(var.frequencies - 10.0)))  # 9.375 Hz, bin 6
    # Exactly on a bin (fps 64 -> bin 10): the amplitude reads close to 5 mm.
    amp = stft_amplitude(np.sin(2 * np.pi * 10 * np.arange(640) / 64.0)[:, None] * 5.0)
    assert int(np.argmax(amp[320, 0])) == 10
    assert amp[320, 0, 10] == pytest.approx(5.0, rel=1e-3)
    # Unrelated keypoints show nothing at that frequency.
    other = var.column("floor_dist_stft_9.38Hz[Paw Front Left]")
    assert np.nanmax(other) < 1e-3


def test_interpolation_fills_short_gaps_only():
    x = np.arange(20, dtype=float)[:, None]
    x[3:5] = np.nan  # gap of 2
    x[10:16] = np.nan  # gap of 6
    x[0] = np.nan  # leading: never filled
    y, n = interpolate_gaps(x, max_gap=3)
    assert n == 2
    assert np.allclose(y[3:5, 0], [3, 4])
    assert np.isnan(y[10:16]).all() and np.isnan(y[0, 0])
    # In the variables: a 3-frame gap is bridged with max_gap 0.05 s at 100 fps, a long one not.
    poses = level_rat(300)
    nose = RAT.index("Nose")
    poses[100:103, nose] = np.nan
    poses[200:230, nose] = np.nan
    var = compute(poses, max_gap_s=0.05)
    col = var.column("floor_dist[Nose]")
    assert np.isfinite(col[100:103]).all()
    assert np.isnan(col[200:230]).all()
    assert var.info["keypoints_interpolated"] == 3
    assert var.info["frames_with_nan"] > 30  # the STFT windows around the long gap too


def test_skipped_frames_become_nan_rows():
    poses = level_rat(100)
    keep = np.r_[0:40, 60:100]
    var = compute_variables(poses[keep], keep, 100.0, RAT, FloorPlane.world([0, 0, 1]))
    assert var.num_frames == 100
    assert np.isnan(var.column("floor_dist[Nose]")[40:60]).all()


def test_floor_plane_distance_and_auto_fit(tmp_path):
    rng = np.random.default_rng(0)
    n = np.array([0.05, -0.03, 1.0])
    n /= np.linalg.norm(n)
    xy = rng.uniform(-400, 400, (4000, 2))
    base = np.c_[xy, -(n[0] * xy[:, 0] + n[1] * xy[:, 1] - 7.0) / n[2]]  # on n.X = 7
    lift = np.where(rng.random(4000) < 0.5, 0.0, rng.uniform(5, 40, 4000))
    feet = base + lift[:, None] * n + rng.normal(0, 0.3, (4000, 3))
    plane = fit_floor(feet, [0, 0, 1])
    assert np.degrees(np.arccos(plane.normal @ n)) < 0.3
    assert plane.offset == pytest.approx(7.0, abs=1.5)
    save_floor(plane, tmp_path / "floor.toml")
    again = load_floor(tmp_path / "floor.toml")
    assert np.allclose(again.normal, plane.normal) and again.offset == pytest.approx(plane.offset)
    with pytest.raises(FloorError, match="paw positions"):
        fit_floor(np.full((10, 3), np.nan), [0, 0, 1])
    (tmp_path / "bad.toml").write_text("offset = 3\n")
    with pytest.raises(FloorError, match="normal"):
        load_floor(tmp_path / "bad.toml")


def test_variables_h5_round_trip(tmp_path):
    data = simulate_rat(3.0, fps=50, seed=1)
    var = variables_from_poses(data, floor="auto")
    assert var.floor.source == "auto"
    path = tmp_path / "x.vars.h5"
    write_variables_h5(var, path, settings={"a": 1})
    back = read_variables_h5(path)
    assert back.names == var.names and back.parts == var.parts and back.types == var.types
    assert np.array_equal(back.values, var.values, equal_nan=True)
    assert np.array_equal(back.involved, var.involved)
    assert back.fps == 50 and np.allclose(back.floor.normal, var.floor.normal)


def test_poses_with_other_keypoints_are_rejected():
    data = simulate_rat(2.0, fps=50)
    other = PoseData(
        data.poses, data.confidence, tuple(f"kp{i}" for i in range(12)), data.frame_index, data.fps
    )
    with pytest.raises(VariablesError, match="do not match skeleton 'rat'"):
        variables_from_poses(other, skeleton="rat")
    reordered = PoseData(
        data.poses, data.confidence, data.keypoints[::-1], data.frame_index, data.fps
    )
    with pytest.raises(VariablesError, match="different order"):
        variables_from_poses(reordered, skeleton="rat")


def test_skeleton_without_body_frame_is_rejected():
    paw = load_skeleton("paw")
    poses = np.zeros((100, paw.num_keypoints, 3))
    with pytest.raises(VariablesError, match=r"no body frame.*\[frame\]"):
        compute_variables(poses, np.arange(100), 100.0, paw, FloorPlane.world([0, 0, 1]))


def test_raised_nose_has_positive_head_elevation():
    poses = level_rat()
    poses[:, RAT.index("Nose"), 2] = 50 + 42 * np.tan(np.radians(30))
    var = compute(poses)
    assert np.allclose(var.column("angle[head_elevation]"), 30, atol=1e-3)
    assert np.allclose(var.column("angle[head_pitch]"), 30, atol=1e-3)
    assert np.allclose(var.column("angle[body_elevation]"), 0, atol=1e-4)
