"""Soft skeleton constraints: lower bone-length variance without a higher error."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.io.poses import PoseData, read_poses_h5, write_poses_h5
from freipose.predict.smooth import SmoothingError, smooth_poses
from freipose.predict.smooth_bones import bone_pairs
from freipose.skeleton import Skeleton

T, FPS = 400, 50.0
KP = ("head", "neck", "tail", "paw")
# head-neck and neck-tail are rigid; neck-paw swings (a limb across a joint)
SKEL = Skeleton("toy4", KP, limbs=(((0,), (1,)), ((1,), (2,)), ((1,), (3,)), ((0, 1), (3,))))


def _session(seed: int = 0) -> tuple[np.ndarray, PoseData]:
    rng = np.random.default_rng(seed)
    t = np.arange(T) / FPS
    neck = np.stack([40 * np.sin(0.8 * t), 30 * np.cos(0.5 * t), 20 + 5 * np.sin(1.3 * t)], -1)
    yaw = 0.6 * np.sin(0.7 * t)
    fwd = np.stack([np.cos(yaw), np.sin(yaw), np.zeros(T)], -1)
    swing = 0.8 * np.sin(2 * np.pi * 1.5 * t)
    reach = 25 + 10 * np.sin(2 * np.pi * 0.9 * t)  # the limb bends: its length varies
    paw = neck + reach[:, None] * np.stack([np.sin(swing), np.zeros(T), -np.cos(swing)], -1)
    truth = np.stack([neck + 30 * fwd, neck, neck - 60 * fwd, paw], 1)
    conf = rng.uniform(0.4, 1.0, (T, 4))
    z = truth + rng.normal(size=truth.shape) * 4.0
    data = PoseData(
        poses=z.astype(np.float32),
        confidence=conf.astype(np.float32),
        keypoints=KP,
        frame_index=np.arange(T),
        fps=FPS,
        skeleton=SKEL,
    )
    return truth, data


def _lengths(x: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    return np.linalg.norm(x[:, pairs[:, 0]] - x[:, pairs[:, 1]], axis=-1)


@pytest.fixture(scope="module")
def fitted():
    truth, data = _session()
    return truth, smooth_poses(data), smooth_poses(data, bones=True)


def test_bone_pairs_are_single_keypoint_limbs():
    assert bone_pairs(SKEL, KP).tolist() == [[0, 1], [1, 2], [1, 3]]
    assert bone_pairs(SKEL, ("neck", "head")).tolist() == [[1, 0]]
    assert bone_pairs(None, KP).shape == (0, 2)


def test_bones_lower_length_variance_without_raising_error(fitted):
    truth, plain, bones = fitted
    pairs = bone_pairs(SKEL, KP)
    sd_plain = _lengths(plain.poses.astype(np.float64), pairs).std(axis=0)
    sd_bones = _lengths(bones.poses.astype(np.float64), pairs).std(axis=0)
    assert np.all(sd_bones[:2] < 0.6 * sd_plain[:2])  # the rigid bones
    assert sd_bones[2] > 0.7 * sd_plain[2]  # the swinging limb is hardly touched
    jpe_plain = np.median(np.linalg.norm(plain.poses - truth, axis=-1))
    jpe_bones = np.median(np.linalg.norm(bones.poses - truth, axis=-1))
    assert jpe_bones <= jpe_plain
    entry = bones.provenance["smoother"]["bones"]
    assert entry["head - neck"]["length_mm"] == pytest.approx(30, abs=1.5)
    np.testing.assert_array_equal(bones.extra["smooth_std"], plain.extra["smooth_std"])


def test_bones_need_a_skeleton(tmp_path):
    _, data = _session(1)
    bare = PoseData(
        poses=data.poses, confidence=data.confidence, keypoints=KP, frame_index=data.frame_index,
        fps=FPS,
    )  # fmt: skip
    with pytest.raises(SmoothingError, match="--bones needs a skeleton"):
        smooth_poses(bare, bones=True)
    write_poses_h5(data, tmp_path / "r.poses.h5")
    run = CliRunner().invoke(
        cli, ["smooth", str(tmp_path / "r.poses.h5"), "-o", str(tmp_path / "s"), "--bones"]
    )
    assert run.exit_code == 0, run.output
    assert "bones" in read_poses_h5(tmp_path / "s" / "r.poses.h5").provenance["smoother"]
