"""Poses with an animal axis: poses.h5, movement, CSV, DLC-3D and NWB exports."""

from __future__ import annotations

import h5py
import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.io.animals import stack_animals
from freipose.io.export import read_dlc3d_csv, read_wide_csv
from freipose.io.poses import PoseData, PosesFormatError, read_poses_h5, write_poses_h5

KPS = ("nose", "tail base", "paw")


def _pair(T: int = 6, seed: int = 0) -> PoseData:
    rng = np.random.default_rng(seed)
    poses = rng.normal(size=(T, 2, 3, 3)).astype(np.float32) * 50
    poses[2, 1, 0] = np.nan
    conf = rng.uniform(size=(T, 2, 3)).astype(np.float32)
    conf[2, 1, 0] = 0
    ident = np.linspace(0.2, 1.0, 2 * T).reshape(T, 2).astype(np.float32)
    extra = {"center": poses.mean(2), "status": np.zeros(T, np.int8)}
    return PoseData(poses, conf, KPS, np.arange(10, 10 + T), 25.0, extra=extra,
                    individuals=("mouse1", "mouse2"), identity_confidence=ident)  # fmt: skip


def test_poses_h5_with_animals_round_trip(tmp_path):
    d = _pair()
    write_poses_h5(d, tmp_path / "p.poses.h5")
    back = read_poses_h5(tmp_path / "p.poses.h5")
    assert back.individuals == ("mouse1", "mouse2") and back.num_animals == 2
    np.testing.assert_array_equal(back.poses, d.poses)
    np.testing.assert_array_equal(back.confidence, d.confidence)
    np.testing.assert_array_equal(back.identity_confidence, d.identity_confidence)
    one = back.animal("mouse2")
    assert one.individuals is None and one.provenance["individual"] == "mouse2"
    np.testing.assert_array_equal(one.poses, d.poses[:, 1])
    np.testing.assert_array_equal(one.extra["center"], d.extra["center"][:, 1])
    np.testing.assert_array_equal(one.extra["status"], d.extra["status"])  # per frame
    again = stack_animals({n: back.animal(n) for n in back.individuals}, back.identity_confidence)
    np.testing.assert_array_equal(again.poses, d.poses)
    np.testing.assert_array_equal(again.extra["center"], d.extra["center"])


def test_single_animal_file_has_no_animal_datasets(tmp_path):
    d = _pair().animal(0)
    write_poses_h5(PoseData(d.poses, d.confidence, KPS, d.frame_index, 25.0),
                   tmp_path / "one.poses.h5")  # fmt: skip
    with h5py.File(tmp_path / "one.poses.h5") as f:
        assert "individuals" not in f and "identity_confidence" not in f
        assert f["poses"].shape == (6, 3, 3)
    back = read_poses_h5(tmp_path / "one.poses.h5")
    assert back.individuals is None and back.num_animals == 1 and back.animal(0) is back
    assert back.animal_poses()[0].shape == (6, 1, 3, 3)


def test_animal_axis_checked():
    d = _pair()
    with pytest.raises(PosesFormatError, match=r"\(T, 3, K, 3\)"):
        PoseData(d.poses, d.confidence, KPS, d.frame_index, 25.0, individuals=("a", "b", "c"))
    with pytest.raises(PosesFormatError, match="unique"):
        PoseData(d.poses, d.confidence, KPS, d.frame_index, 25.0, individuals=("a", "a"))
    with pytest.raises(PosesFormatError, match="center"):
        PoseData(d.poses, d.confidence, KPS, d.frame_index, 25.0, individuals=("a", "b"),
                 extra={"center": np.zeros((6, 3))})  # fmt: skip
    with pytest.raises(PosesFormatError, match="identity_confidence"):
        PoseData(d.poses, d.confidence, KPS, d.frame_index, 25.0, individuals=("a", "b"),
                 identity_confidence=np.full((6, 2), 2.0))  # fmt: skip
    with pytest.raises(PosesFormatError, match="no animal 'rat'"):
        d.animal("rat")


def _export(path, *args):
    r = CliRunner().invoke(cli, ["export", str(path), *args])
    assert r.exit_code == 0, r.output
    return r


def test_exports_keep_individuals(tmp_path):
    d = _pair()
    src = tmp_path / "pair.poses.h5"
    write_poses_h5(d, src)
    _export(src, "--format", "csv")
    df = pd.read_csv(tmp_path / "pair.csv", dtype={"individual": str})
    assert list(df["individual"][:4]) == ["mouse1", "mouse2", "mouse1", "mouse2"]
    frames, poses, conf, kps = read_wide_csv(tmp_path / "pair.csv")
    assert kps == KPS and len(frames) == 12
    np.testing.assert_allclose(poses.reshape(6, 2, 3, 3), d.poses, rtol=1e-6)
    np.testing.assert_allclose(df["identity_confidence"].to_numpy().reshape(6, 2),
                               d.identity_confidence, rtol=1e-6)  # fmt: skip
    _export(src, "--format", "dlc3d")
    frames, poses, kps = read_dlc3d_csv(tmp_path / "pair.dlc3d.csv")
    np.testing.assert_allclose(poses, d.poses, rtol=1e-6)
    np.testing.assert_array_equal(frames, d.frame_index)
    r = CliRunner().invoke(cli, ["export", str(src), "--format", "anipose"])
    assert r.exit_code != 0 and "--animal" in r.output
    _export(src, "--format", "anipose", "--animal", "mouse2", "-o", str(tmp_path / "m2.csv"))
    r = CliRunner().invoke(cli, ["export", str(src), "--format", "csv", "--animal", "rat",
                                 "-o", str(tmp_path / "x.csv")])  # fmt: skip
    assert r.exit_code != 0 and "mouse1" in r.output


def test_movement_export_has_the_individuals(tmp_path):
    xr = pytest.importorskip("xarray")
    d = _pair()
    src = tmp_path / "pair.poses.h5"
    write_poses_h5(d, src)
    _export(src, "--format", "movement")
    ds = xr.open_dataset(tmp_path / "pair.nc")
    assert list(ds["individuals"].values) == ["mouse1", "mouse2"]
    np.testing.assert_array_equal(
        ds["position"].sel(individuals="mouse2").transpose("time", "keypoints", "space").values,
        d.poses[:, 1],
    )
    ds.close()
    back = read_poses_h5(tmp_path / "pair.nc")
    assert back.individuals == d.individuals
    np.testing.assert_array_equal(back.poses, d.poses)
    np.testing.assert_array_equal(back.identity_confidence, d.identity_confidence)


def test_nwb_export_one_pose_estimation_per_animal(tmp_path):
    pytest.importorskip("pynwb")
    pytest.importorskip("ndx_pose")
    from freipose.io.export import read_nwb

    d = _pair()
    src = tmp_path / "pair.poses.h5"
    write_poses_h5(d, src)
    _export(src, "--format", "nwb")
    for i, name in enumerate(d.individuals):
        _, poses, conf, kps = read_nwb(tmp_path / "pair.nwb", name)
        assert kps == KPS
        np.testing.assert_allclose(poses, d.poses[:, i], rtol=1e-6)
