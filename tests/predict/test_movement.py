"""movement interop: export --format movement, read back by movement and by FreiPose."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner
from predict_helpers import small_rig

from freipose.cli.main import cli
from freipose.io.movement import MovementFormatError
from freipose.io.poses import PoseData, read_poses_h5, write_poses_h5
from freipose.skeleton import load_skeleton

pytest.importorskip(
    "xarray", reason="movement files need the extra: pip install 'freipose[movement]'"
)
movement_io = pytest.importorskip(
    "movement.io", reason="the round trip needs movement: pip install 'freipose[movement]'"
)

T = 20


@pytest.fixture
def poses_file(tmp_path):
    rng = np.random.default_rng(5)
    skel = load_skeleton("rat")
    k = len(skel.keypoints)
    poses = rng.normal(0, 60, (T, k, 3)).astype(np.float32)
    conf = rng.uniform(0.2, 1.0, (T, k)).astype(np.float32)
    poses[3] = np.nan
    conf[3] = 0
    data = PoseData(
        poses=poses, confidence=conf, keypoints=skel.keypoints, frame_index=np.arange(50, 50 + T),
        fps=30.0, up=[0, 0, 1], calibration=small_rig(3), skeleton=skel,
        provenance={"session": "rec3"},
    )  # fmt: skip
    path = tmp_path / "rec3.poses.h5"
    write_poses_h5(data, path)
    return path


def test_export_movement_round_trip(poses_file, tmp_path):
    res = CliRunner().invoke(cli, ["export", str(poses_file), "--format", "movement",
                                   "-o", str(tmp_path / "out")])  # fmt: skip
    assert res.exit_code == 0, res.output
    nc = tmp_path / "out" / "rec3.nc"
    orig = read_poses_h5(poses_file)
    import xarray as xr

    ds = xr.open_dataset(nc)
    assert ds["position"].dims == ("time", "space", "keypoints", "individuals")
    assert ds["confidence"].dims == ("time", "keypoints", "individuals")
    assert ds.attrs["ds_type"] == "poses" and ds.attrs["fps"] == 30.0
    pos = ds["position"].values[..., 0].transpose(0, 2, 1)
    np.testing.assert_array_equal(pos, orig.poses)  # exact, NaN included
    np.testing.assert_array_equal(ds["confidence"].values[..., 0], orig.confidence)
    assert tuple(ds["keypoints"].values) == orig.keypoints
    np.testing.assert_allclose(ds["time"].values, orig.frame_index / 30.0)
    ds.close()
    back = read_poses_h5(nc)
    np.testing.assert_array_equal(back.poses, orig.poses)
    np.testing.assert_array_equal(back.confidence, orig.confidence)
    np.testing.assert_array_equal(back.frame_index, orig.frame_index)
    assert back.keypoints == orig.keypoints and back.fps == orig.fps
    assert back.skeleton is not None and back.calibration is not None
    assert back.provenance["session"] == "rec3"


def test_a_dataset_made_by_movement_reads_as_poses(tmp_path):
    from movement.io import load_poses

    pos = np.random.default_rng(0).normal(size=(8, 3, 2, 1)).astype(np.float32)
    conf = np.full((8, 2, 1), 0.5, np.float32)
    ds = load_poses.from_numpy(pos, conf, individual_names=["rat"], keypoint_names=["a", "b"],
                               fps=25.0, source_software="test")  # fmt: skip
    ds.to_netcdf(tmp_path / "m.nc")
    back = read_poses_h5(tmp_path / "m.nc")
    np.testing.assert_array_equal(back.poses, pos[..., 0].transpose(0, 2, 1))
    np.testing.assert_array_equal(back.frame_index, np.arange(8))
    assert back.keypoints == ("a", "b") and back.fps == 25.0


def test_two_individuals_read_with_an_animal_axis(tmp_path):
    from movement.io import load_poses

    pos = np.random.default_rng(1).normal(size=(4, 3, 2, 2)).astype(np.float32)
    ds = load_poses.from_numpy(pos, individual_names=["a", "b"], fps=10.0, source_software="t")
    ds.to_netcdf(tmp_path / "two.nc")
    back = read_poses_h5(tmp_path / "two.nc")
    assert back.individuals == ("a", "b") and back.poses.shape == (4, 2, 2, 3)
    np.testing.assert_array_equal(back.poses[:, 1], pos[..., 1].transpose(0, 2, 1))
    np.testing.assert_array_equal(back.animal("b").poses, pos[..., 1].transpose(0, 2, 1))


def test_2d_dataset_refused(tmp_path):
    from movement.io import load_poses

    ds = load_poses.from_numpy(np.zeros((4, 2, 2, 1), np.float32), fps=10.0, source_software="t")
    ds.to_netcdf(tmp_path / "flat.nc")
    with pytest.raises(MovementFormatError, match="3D"):
        read_poses_h5(tmp_path / "flat.nc")
