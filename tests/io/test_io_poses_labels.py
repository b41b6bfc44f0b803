"""poses.h5 and labels.h5: round trips, validation and error messages."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from freipose.io.labels import (
    LabelSet,
    LabelsFormatError,
    SessionInfo,
    read_labels_h5,
    write_labels_h5,
)
from freipose.io.poses import PoseData, PosesFormatError, read_poses_h5, write_poses_h5
from freipose.skeleton import load_skeleton
from freipose.testing import make_circle_rig


def _pose_data(rng: np.random.Generator, t: int = 20) -> PoseData:
    skel = load_skeleton("rat")
    poses = rng.normal(0, 50, size=(t, 12, 3))
    poses[3, 4] = np.nan
    conf = rng.uniform(0, 1, size=(t, 12))
    conf[3, 4] = 0
    return PoseData(
        poses=poses,
        confidence=conf,
        keypoints=skel.keypoints,
        frame_index=np.arange(t) * 2 + 100,
        fps=50.0,
        up=(0, 0, 2),
        calibration=make_circle_rig(3),
        skeleton=skel,
        provenance={"model": "abc123", "videos": ["a.mp4"]},
        extra={"center": rng.normal(size=(t, 3)), "points2d": rng.normal(size=(t, 3, 12, 2))},
    )


def test_poses_round_trip(tmp_path, rng):
    data = _pose_data(rng)
    p = tmp_path / "run.poses.h5"
    write_poses_h5(data, p)
    back = read_poses_h5(p)
    np.testing.assert_array_equal(back.poses, data.poses)  # NaN in the same places
    assert back.poses.dtype == np.float32 and back.confidence.dtype == np.float32
    np.testing.assert_array_equal(back.confidence, data.confidence)
    assert back.keypoints == data.keypoints and back.fps == 50.0
    np.testing.assert_array_equal(back.frame_index, data.frame_index)
    np.testing.assert_allclose(back.up, [0, 0, 1])  # normalised
    assert back.calibration.allclose(data.calibration)
    assert back.skeleton.to_dict() == data.skeleton.to_dict()
    assert back.provenance == {"model": "abc123", "videos": ["a.mp4"]}
    np.testing.assert_allclose(back.extra["points2d"], data.extra["points2d"])
    np.testing.assert_allclose(back.times, data.frame_index / 50.0)
    with h5py.File(p) as f:
        assert f.attrs["units"] == "mm" and f["keypoints"][0].decode() == "Ear Right"


def test_pose_data_validation(rng):
    kw = dict(keypoints=["a", "b"], frame_index=np.arange(4), fps=30)
    with pytest.raises(ValueError, match=r"\(T, K, 3\)"):
        PoseData(poses=np.zeros((4, 2)), confidence=np.zeros((4, 2)), **kw)
    with pytest.raises(ValueError, match="confidence must have shape"):
        PoseData(poses=np.zeros((4, 2, 3)), confidence=np.zeros((4, 3)), **kw)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        PoseData(poses=np.zeros((4, 2, 3)), confidence=np.full((4, 2), 2.0), **kw)
    with pytest.raises(ValueError, match="fps"):
        PoseData(
            poses=np.zeros((4, 2, 3)),
            confidence=np.zeros((4, 2)),
            keypoints=["a", "b"],
            frame_index=np.arange(4),
            fps=0,
        )
    with pytest.raises(ValueError, match="3 keypoint names"):
        PoseData(
            poses=np.zeros((4, 2, 3)),
            confidence=np.zeros((4, 2)),
            keypoints=["a", "b", "c"],
            frame_index=np.arange(4),
            fps=30,
        )
    with pytest.raises(ValueError, match="do not match"):
        PoseData(
            poses=np.zeros((4, 2, 3)),
            confidence=np.zeros((4, 2)),
            skeleton=load_skeleton("rat"),
            **kw,
        )
    with pytest.raises(ValueError, match="extra dataset 'x'"):
        PoseData(
            poses=np.zeros((4, 2, 3)), confidence=np.zeros((4, 2)), extra={"x": np.zeros(3)}, **kw
        )
    with pytest.raises(ValueError, match="up must be"):
        PoseData(poses=np.zeros((4, 2, 3)), confidence=np.zeros((4, 2)), up=(0, 0, 0), **kw)


def test_poses_read_errors(tmp_path, rng):
    p = tmp_path / "p.h5"
    with pytest.raises(FileNotFoundError, match="not found"):
        read_poses_h5(p)
    write_poses_h5(_pose_data(rng), p)
    with h5py.File(p, "a") as f:
        del f.attrs["up"]
    with pytest.raises(PosesFormatError, match="missing the 'up' attribute"):
        read_poses_h5(p)
    np.testing.assert_allclose(read_poses_h5(p, require_up=False).up, [0, 0, 1])
    with h5py.File(p, "a") as f:
        del f["confidence"]
    with pytest.raises(PosesFormatError, match=r"missing datasets \['confidence'\]"):
        read_poses_h5(p)
    write_poses_h5(_pose_data(rng), p)
    with h5py.File(p, "a") as f:
        f.attrs["units"] = "m"
    with pytest.raises(PosesFormatError, match="units are 'm'"):
        read_poses_h5(p)
    write_poses_h5(_pose_data(rng), p)
    raw = p.read_bytes()
    p.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(PosesFormatError, match="truncated"):
        read_poses_h5(p)
    p.write_text("hello")
    with pytest.raises(PosesFormatError, match="not a readable HDF5"):
        read_poses_h5(p)


def test_poses_write_is_atomic(tmp_path, rng):
    p = tmp_path / "p.h5"
    write_poses_h5(_pose_data(rng), p)
    before = p.read_bytes()

    bad = _pose_data(rng)
    object.__setattr__(bad, "extra", {"bad": object()})  # h5py cannot store an object
    with pytest.raises(TypeError):
        write_poses_h5(bad, p)
    assert p.read_bytes() == before
    assert [q.name for q in tmp_path.iterdir()] == ["p.h5"]  # no temporary left behind


def _labels(rng: np.random.Generator) -> LabelSet:
    rig_a = make_circle_rig(3)
    rig_b = make_circle_rig(4).subset(["cam0", "cam1", "cam3"]).with_metadata(world="b")
    rig_b = type(rig_b)(
        tuple(c.replace(name=n) for c, n in zip(rig_b, ["cam0", "cam1", "cam3"])), rig_b.metadata
    )
    n, v, k = 5, 4, 2
    p2 = rng.uniform(0, 640, size=(n, v, k, 2))
    p2[0, 2, 1] = np.nan
    p2[:3, 3] = np.nan  # session a has no cam3
    p3 = rng.normal(size=(n, k, 3))
    p3[1] = np.nan
    return LabelSet(
        session=["a", "a", "a", "b", "b"],
        frame_index=[0, 10, 20, 5, 6],
        points2d=p2,
        points3d=p3,
        cameras=("cam0", "cam1", "cam2", "cam3"),
        keypoints=("Nose", "Tail"),
        sessions={
            "a": SessionInfo(rig_a, {"cam0": "a/cam0.mp4"}, 30.0),
            "b": SessionInfo(rig_b, {}, None),
        },
        visible2d=np.isfinite(p2[..., 0]),
    )


def test_labels_round_trip_and_select(tmp_path, rng):
    labels = _labels(rng)
    p = tmp_path / "labels.h5"
    write_labels_h5(labels, p)
    back = read_labels_h5(p)
    np.testing.assert_array_equal(back.points2d, labels.points2d)
    np.testing.assert_array_equal(back.points3d, labels.points3d)
    np.testing.assert_array_equal(back.visible2d, labels.visible2d)
    assert list(back.session) == ["a", "a", "a", "b", "b"] and back.cameras == labels.cameras
    assert back.rig_for("a").allclose(labels.rig_for("a"))
    assert back.rig_for("b").names == ["cam0", "cam1", "cam3"]
    assert back.sessions["a"].videos == {"cam0": "a/cam0.mp4"} and back.sessions["a"].fps == 30.0
    assert back.sessions["b"].fps is None and back.rig_for("zzz") is None
    sub = back.select(back.session == "b")
    assert len(sub) == 2 and set(sub.sessions) == {"b"}
    assert back.select([0, 2]).frame_index.tolist() == [0, 20]


def test_labels_validation_and_errors(tmp_path, rng):
    labels = _labels(rng)
    with pytest.raises(ValueError, match="points2d must have shape"):
        LabelSet(["a"], [0], np.zeros((1, 2, 2, 2)), np.zeros((1, 2, 3)), ("c0",), ("k0", "k1"))
    with pytest.raises(ValueError, match="points3d must have shape"):
        LabelSet(["a"], [0], np.zeros((1, 1, 2, 2)), np.zeros((1, 3, 3)), ("c0",), ("k0", "k1"))
    with pytest.raises(ValueError, match="unique"):
        LabelSet(["a"], [0], np.zeros((1, 1, 2, 2)), np.zeros((1, 2, 3)), ("c0",), ("k0", "k0"))
    with pytest.raises(ValueError, match="not in cameras"):
        LabelSet(
            ["a"],
            [0],
            np.zeros((1, 1, 2, 2)),
            np.zeros((1, 2, 3)),
            ("c0",),
            ("k0", "k1"),
            {"a": SessionInfo(make_circle_rig(2))},
        )
    p = tmp_path / "labels.h5"
    with pytest.raises(FileNotFoundError):
        read_labels_h5(p)
    write_labels_h5(labels, p)
    with h5py.File(p, "a") as f:
        del f["points3d"]
    with pytest.raises(LabelsFormatError, match=r"missing datasets \['points3d'\]"):
        read_labels_h5(p)
    write_labels_h5(labels, p)
    with h5py.File(p, "a") as f:
        del f["frame_index"]
        f["frame_index"] = np.arange(3)
    with pytest.raises(LabelsFormatError, match="frame_index must have shape"):
        read_labels_h5(p)
    write_labels_h5(labels, p)
    raw = p.read_bytes()
    p.write_bytes(raw[: len(raw) // 3])
    with pytest.raises(LabelsFormatError, match="truncated"):
        read_labels_h5(p)
