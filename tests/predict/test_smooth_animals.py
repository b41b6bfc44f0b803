"""Smoothing poses of several animals: each animal on its own, the animal axis kept."""

from __future__ import annotations

import numpy as np
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.io.animals import stack_animals
from freipose.io.poses import PoseData, read_poses_h5, write_poses_h5
from freipose.predict.smooth import smooth_poses

T, K, FPS = 300, 3, 50.0


def _animal(seed: int) -> PoseData:
    """A noisy walk of K keypoints (the second animal far from the first)."""
    rng = np.random.default_rng(seed)
    t = np.arange(T) / FPS
    truth = 40 * np.sin(2 * np.pi * 0.5 * t)[:, None, None] + rng.normal(0, 30, (1, K, 3))
    truth = truth + 200.0 * seed
    z = (truth + rng.normal(0, 2.0, (T, K, 3))).astype(np.float32)
    conf = np.full((T, K), 0.9, np.float32)
    return PoseData(z, conf, tuple(f"kp{k}" for k in range(K)), np.arange(T), FPS)


def _pair() -> PoseData:
    ident = np.full((T, 2), 0.9, np.float32)
    return stack_animals({"animal_0": _animal(1), "animal_1": _animal(2)}, ident)


def test_each_animal_smoothed_as_if_alone():
    pair = _pair()
    out = smooth_poses(pair, source="pair.poses.h5")
    assert out.individuals == ("animal_0", "animal_1") and out.poses.shape == (T, 2, K, 3)
    for i, name in enumerate(pair.individuals):
        alone = smooth_poses(pair.animal(name))
        np.testing.assert_array_equal(out.poses[:, i], alone.poses)
        np.testing.assert_array_equal(out.extra["smooth_std"][:, i], alone.extra["smooth_std"])
        np.testing.assert_array_equal(
            out.extra["smooth_offset"][:, i], alone.extra["smooth_offset"]
        )
        assert (
            out.provenance["smoother"]["animals"][name]["params"]
            == (alone.provenance["smoother"]["params"])
        )
    np.testing.assert_array_equal(out.identity_confidence, pair.identity_confidence)


def test_smooth_command_on_a_file_of_two_animals(tmp_path):
    src = tmp_path / "pair.poses.h5"
    write_poses_h5(_pair(), src)
    res = CliRunner().invoke(cli, ["smooth", str(src), "-o", str(tmp_path / "smooth")])
    assert res.exit_code == 0, res.output
    back = read_poses_h5(tmp_path / "smooth" / "pair.poses.h5")
    assert back.individuals == ("animal_0", "animal_1")
    assert back.extra["smooth_weight"].shape == (T, 2, K)
    assert np.isfinite(back.poses).all()
