"""Export round trips: wide CSV, Anipose CSV, DLC-3D CSV and NWB read back equal."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner
from predict_helpers import small_rig

from freipose.cli.main import cli
from freipose.io import export
from freipose.io.poses import PoseData, read_poses_h5, write_poses_h5
from freipose.skeleton import load_skeleton

T = 30


@pytest.fixture(scope="module")
def poses_file(tmp_path_factory):
    rng = np.random.default_rng(3)
    skel = load_skeleton("rat")
    K = len(skel.keypoints)
    rig = small_rig(4)
    poses = rng.normal(0, 60, (T, K, 3)).astype(np.float32)
    poses[..., 2] += 100
    conf = rng.uniform(0.2, 1.0, (T, K)).astype(np.float32)
    poses[[4, 5]] = np.nan
    conf[[4, 5]] = 0
    poses[9, 3] = np.nan
    conf[9, 3] = 0
    p2 = rig.project(poses.astype(np.float64)).astype(np.float32)  # (T, C, K, 2)
    p2 = p2 + rng.normal(0, 1.0, p2.shape).astype(np.float32)
    data = PoseData(
        poses=poses,
        confidence=conf,
        keypoints=skel.keypoints,
        frame_index=np.arange(100, 100 + T),
        fps=30.0,
        calibration=rig,
        skeleton=skel,
        provenance={"session": "rec7", "videos": {"cam0": "cam0.mp4"}, "freipose_version": "0.1.0"},
        extra={"points2d": p2, "confidence2d": np.ones(p2.shape[:3], np.float32)},
    )
    path = tmp_path_factory.mktemp("exp") / "rec7.poses.h5"
    write_poses_h5(data, path)
    return path


def test_wide_csv_round_trip_names_units_and_layout(poses_file, tmp_path):
    import json

    out = export.export_poses(poses_file, "csv", tmp_path / "p.csv")
    d = read_poses_h5(poses_file)
    frames, poses, conf, kps = export.read_wide_csv(out)
    assert kps == d.keypoints
    np.testing.assert_array_equal(frames, d.frame_index)
    np.testing.assert_array_equal(poses.astype(np.float32), d.poses)  # exact, NaN included
    np.testing.assert_array_equal(conf.astype(np.float32), d.confidence)
    df = pd.read_csv(out)
    assert list(df.columns[:6]) == [
        "frame",
        "time_s",
        "Ear_Right_x_mm",
        "Ear_Right_y_mm",
        "Ear_Right_z_mm",
        "Ear_Right_confidence",
    ]
    assert not any(" " in c for c in df.columns)
    assert df["time_s"].iloc[0] == pytest.approx(100 / 30)
    assert df.loc[4, "Ear_Right_x_mm"] != df.loc[4, "Ear_Right_x_mm"]  # empty cell -> NaN
    side = json.loads((tmp_path / "p.csv.json").read_text())
    assert side["layout"] == "wide: one row per frame"
    assert side["columns"]["Paw_Front_Right_z_mm"] == {
        "keypoint": "Paw Front Right", "quantity": "z", "unit": "mm"
    }  # fmt: skip
    assert set(side["columns"]) == set(df.columns)
    # without the sidecar the names come from the columns
    (tmp_path / "p.csv.json").unlink()
    assert export.read_wide_csv(out)[3][0] == "Ear_Right"
    with pytest.raises(export.ExportError, match="same CSV column names"):
        export._wide_columns(("a b", "a_b"))


def test_anipose_csv(poses_file, tmp_path):
    out = export.export_poses(poses_file, "anipose", tmp_path / "a.csv")
    d = read_poses_h5(poses_file)
    fnum, poses, score, kps = export.read_anipose_csv(out)
    assert kps == d.keypoints
    np.testing.assert_array_equal(fnum, d.frame_index)
    np.testing.assert_array_equal(poses.astype(np.float32), d.poses)
    found = np.isfinite(d.poses).all(-1)
    np.testing.assert_array_equal(score[found].astype(np.float32), d.confidence[found])
    assert np.isnan(score[~found]).all()
    df = pd.read_csv(out)
    for col in ("Nose_error", "Nose_ncams", "M_00", "M_22", "center_2", "fnum"):
        assert col in df.columns
    err = df[[f"{k}_error" for k in kps]].to_numpy()
    assert np.nanmedian(err) == pytest.approx(1.25, abs=0.5)  # 2D noise of sigma 1 px
    assert np.isnan(err[~found]).all()
    assert set(df["Nose_ncams"].dropna()) == {4.0}


def test_dlc3d_csv_round_trip(poses_file, tmp_path):
    out = export.export_poses(poses_file, "dlc3d", tmp_path / "d.csv")
    d = read_poses_h5(poses_file)
    with open(out) as f:
        head = [next(f).split(",")[0] for _ in range(3)]
    assert head == ["scorer", "bodyparts", "coords"]
    frames, poses, kps = export.read_dlc3d_csv(out)
    assert kps == d.keypoints
    np.testing.assert_array_equal(frames, d.frame_index)
    np.testing.assert_array_equal(poses.astype(np.float32), d.poses)


def test_nwb_round_trip(poses_file, tmp_path):
    pytest.importorskip("pynwb", reason="NWB export needs the optional extra: pip install pynwb")
    pytest.importorskip(
        "ndx_pose", reason="NWB export needs the optional extra: pip install ndx-pose"
    )
    out = export.export_poses(poses_file, "nwb")
    assert out == poses_file.with_name("rec7.nwb")
    d = read_poses_h5(poses_file)
    times, poses, conf, kps = export.read_nwb(out)
    assert kps == d.keypoints
    np.testing.assert_allclose(times, d.frame_index / 30.0)
    np.testing.assert_array_equal(poses.astype(np.float32), d.poses)
    np.testing.assert_array_equal(conf.astype(np.float32), d.confidence)
    import pynwb

    with pynwb.NWBHDF5IO(str(out), "r") as io:
        nwb = io.read()
        pe = nwb.processing["behavior"]["PoseEstimation"]
        s = pe.pose_estimation_series["Nose"]
        assert s.unit == "mm" and s.data.shape == (T, 3)
        assert pe.source_software == "FreiPose"
        assert nwb.identifier == "rec7"
        assert len(pe.skeleton.edges[:]) > 0


def test_export_command_writes_into_a_folder(poses_file, tmp_path):
    args = [
        "export",
        str(poses_file),
        str(poses_file),
        "--format",
        "dlc3d",
        "-o",
        str(tmp_path / "o"),
    ]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 0, res.output
    assert (tmp_path / "o" / "rec7.dlc3d.csv").is_file()
    res = CliRunner().invoke(
        cli, ["export", str(poses_file), "--format", "nwb", "--start-time", "x"]
    )
    assert res.exit_code != 0 and "ISO time" in res.output


def test_default_names_and_unknown_format(poses_file):
    assert export.default_output(poses_file, "anipose").name == "rec7.anipose.csv"
    assert export.default_output(poses_file, "csv").name == "rec7.csv"
    with pytest.raises(export.ExportError, match="unknown export format"):
        export.export_poses(poses_file, "xlsx")
