"""Social variables of several animals: distances, facing, contact, per-animal variables."""

from __future__ import annotations

import numpy as np
import pytest

from freipose.analysis.floor import FloorPlane
from freipose.analysis.social import SocialConfig, animal_variables, social_variables
from freipose.analysis.variables import VariablesError, compute_variables
from freipose.skeleton import load_skeleton

RAT = load_skeleton("rat")
FPS = 50.0


def _rat(head: np.ndarray, heading: float) -> np.ndarray:
    """(K, 3) a schematic rat: keypoints placed along ``heading`` behind the ear midpoint."""
    f = np.array([np.cos(heading), np.sin(heading), 0.0])
    left = np.array([-np.sin(heading), np.cos(heading), 0.0])
    at = {
        "Ear Right": -10 * left, "Ear Left": 10 * left, "Eye Right": 15 * f - 8 * left,
        "Eye Left": 15 * f + 8 * left, "Nose": 35 * f, "Tail": -150 * f,
        "Paw Front Right": -30 * f - 20 * left, "Paw Front Left": -30 * f + 20 * left,
        "Paw Back Right Ankle": -110 * f - 25 * left, "Paw Back Left Ankle": -110 * f + 25 * left,
        "Paw Back Right Tip": -95 * f - 30 * left, "Paw Back Left Tip": -95 * f + 30 * left,
    }  # fmt: skip
    return np.stack([np.r_[head[:2], 40.0] + at[k] for k in RAT.keypoints])


def _two_rats(n: int = 100) -> np.ndarray:
    """Rat 0 walks along +x towards rat 1, which stands at x=300 facing away (+x)."""
    poses = np.zeros((n, 2, RAT.num_keypoints, 3))
    for t in range(n):
        poses[t, 0] = _rat(np.array([-200 + 4.0 * t, 0.0]), 0.0)
        poses[t, 1] = _rat(np.array([300.0, 0.0]), 0.0)
    return poses


def test_distances_facing_and_contact_of_a_known_approach() -> None:
    poses = _two_rats()
    s0 = social_variables(poses, RAT, FPS, animal=0)
    s1 = social_variables(poses, RAT, FPS, animal=1)
    col = dict(zip(s0.names, s0.values.T, strict=True))
    col1 = dict(zip(s1.names, s1.values.T, strict=True))
    head0 = -200 + 4.0 * np.arange(100)
    np.testing.assert_allclose(col["social_dist[head-head of animal 1]"], 300 - head0, atol=1e-3)
    np.testing.assert_allclose(col["social_dist[head-tail of animal 1]"], np.abs(150 - head0),
                               atol=1e-3)  # fmt: skip
    # rat 0 closes in at 4 mm per frame = 200 mm/s
    np.testing.assert_allclose(col["social_approach[animal 1]"][1:-1], -200.0, atol=1e-2)
    # rat 0 faces rat 1 (0 deg) while behind it; rat 1 has its back to rat 0 (180 deg)
    assert col["facing[animal 1]"][0] < 1.0
    assert col1["facing[animal 0]"][0] > 179.0
    # contact: rat 0's nose (head + 35) comes within 15 mm of rat 1's tail (x = 150) once its
    # head passes x = 100, at frame 76
    contact = col["contact[animal 1]"]
    assert not contact[:76].any() and contact[76:86].all()
    np.testing.assert_allclose(col["social_min_dist[animal 1]"], col1["social_min_dist[animal 0]"])
    assert s0.involved.shape == (len(s0.names), RAT.num_keypoints)
    assert set(s0.kinds) == {"social_dist", "social_min_dist", "social_approach", "facing",
                             "contact"}  # fmt: skip


def test_animal_variables_append_social_columns_and_keep_the_single_animal_ones() -> None:
    poses = _two_rats(120)
    rng = np.random.default_rng(0)
    poses = poses + rng.normal(0, 1, poses.shape)
    poses[50:53, 1, 10] = np.nan  # a short gap in rat 1's nose is filled
    floor = FloorPlane(np.array([0.0, 0, 1]))
    frames = np.arange(120)
    var = animal_variables(poses, frames, FPS, RAT, floor, animal=0,
                           social=SocialConfig(pairs=(("Nose", "Tail"),)))  # fmt: skip
    alone = compute_variables(poses[:, 0], frames, FPS, RAT, floor)
    v = alone.values.shape[1]
    np.testing.assert_array_equal(var.values[:, :v], alone.values)
    assert var.names[:v] == alone.names
    assert "social_dist[Nose-Tail of animal 1]" in var.names
    assert var.info["animal"] == 0 and var.info["animals"] == 2
    assert np.isfinite(var.column("social_dist[head-head of animal 1]")).all()


def test_three_animals_and_bad_input() -> None:
    poses = np.concatenate([_two_rats(20), _two_rats(20)[:, :1] + [0, 300, 0]], axis=1)
    s = social_variables(poses, RAT, FPS, animal=2)
    assert any("animal 0" in n for n in s.names) and any("animal 1" in n for n in s.names)
    assert not any("animal 2" in n for n in s.names)
    with pytest.raises(VariablesError, match="at least 2 animals"):
        social_variables(poses[:, :1], RAT, FPS, animal=0)
    with pytest.raises(VariablesError, match=r"\(T, A, 12, 3\)"):
        social_variables(poses[:, :, :5], RAT, FPS, animal=0)
    with pytest.raises(VariablesError, match="animal must be"):
        social_variables(poses, RAT, FPS, animal=3)
    with pytest.raises(VariablesError, match="no keypoint"):
        social_variables(poses, RAT, FPS, 0, config=SocialConfig(pairs=(("Snout", "Tail"),)))
    with pytest.raises(VariablesError, match="contact_mm"):
        SocialConfig(contact_mm=0)
