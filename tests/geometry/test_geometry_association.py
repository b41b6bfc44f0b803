"""Cross-view association of several animals' detections into 3D hypotheses."""

from __future__ import annotations

import numpy as np
import pytest
from social_scene import observe, social_scene

from freipose.detect.boxes import box_centers, box_sizes
from freipose.geometry import project_rig
from freipose.geometry.association import AssociationConfig, associate
from freipose.synth.rig import default_rig

RIG = default_rig(7, seed=0)


def _majority(labels: list[int]) -> int:
    u, cnt = np.unique(labels, return_counts=True)
    return int(u[np.argmax(cnt)])


def test_exact_points_of_three_animals_are_grouped_and_triangulated() -> None:
    rng = np.random.default_rng(1)
    X = np.array([[-150.0, 80, 40], [120, -60, 40], [20, 150, 60]])
    uv = project_rig(X, RIG)  # (C, 3, 2)
    points, order = [], []
    for c in range(len(RIG)):
        perm = rng.permutation(3)  # the views list the animals in any order
        points.append(uv[c, perm] + rng.normal(0, 0.3, (3, 2)))
        order.append(perm)
    A = associate(points, RIG)
    assert len(A) == 3
    assert (A.n_views == len(RIG)).all()
    for h in range(3):
        animal = order[0][A.members[h, 0]]
        assert all(order[c][A.members[h, c]] == animal for c in range(len(RIG)))
        assert np.linalg.norm(A.points[h] - X[animal]) < 3.0
    assert all(len(left) == 0 for left in A.leftover)
    assert np.nanmax(A.errors) < 2.0


def test_scene_with_occlusion_merged_and_false_boxes() -> None:
    """Every animal seen by 3+ views is found, members are right, false boxes are left over."""
    scene = social_scene(3, n_frames=90, seed=0)
    obs = observe(scene, RIG, seed=1, p_drop=0.15, p_false=0.3, hidden={(0, 2): (0, 89)})
    right = wrong = found = expected = false_in = 0
    for t in range(90):
        b = obs.boxes[t]
        sz = [np.sqrt(np.prod(box_sizes(x), -1)) for x in b]
        A = associate(
            [box_centers(x) for x in b],
            RIG,
            tolerances=[np.maximum(8.0, 0.25 * s) for s in sz],
            sizes=sz,
            config=AssociationConfig(min_views=3),
        )
        assert A.members.shape == (len(A), len(RIG))
        seen = obs.visible[t].sum(0) >= 3  # (A,)
        got = set()
        for h in range(len(A)):
            labs = [int(obs.truth[t][c][A.members[h, c]]) for c in range(7) if A.members[h, c] >= 0]
            m = _majority(labs)
            right += sum(x == m for x in labs)
            wrong += sum(x != m for x in labs)
            false_in += sum(x == -1 for x in labs)
            if m >= 0:
                got.add(m)
                assert np.linalg.norm(A.points[h] - scene.centres[t, m]) < 40
        expected += int(seen.sum())
        found += len(got & set(np.flatnonzero(seen)))
        assert A.members[:, 2][A.members[:, 2] >= 0].size <= len(obs.boxes[t][2])
    assert found == expected
    assert wrong <= 0.005 * (right + wrong)
    assert false_in <= 2


def test_an_animal_seen_by_two_views_only() -> None:
    X = np.array([[-100.0, 50, 40], [100, -50, 40]])
    uv = project_rig(X, RIG)
    points = [uv[c] if c in (0, 3) else uv[c, :1] for c in range(len(RIG))]
    A = associate(points, RIG, config=AssociationConfig(min_views=2))
    assert len(A) == 2
    assert list(A.n_views) == [len(RIG), 2]
    assert np.linalg.norm(A.points[1] - X[1]) < 2.0
    assert len(associate(points, RIG, config=AssociationConfig(min_views=3))) == 1


def test_bounds_limits_and_bad_input() -> None:
    X = np.array([[-100.0, 50, 40], [100, -50, 40]])
    uv = list(project_rig(X, RIG))
    assert len(associate(uv, RIG, config=AssociationConfig(max_hypotheses=1))) == 1
    bounds = np.array([[-300, 0], [-300, 300], [0, 200]])
    A = associate(uv, RIG, bounds=bounds)
    assert len(A) == 1 and A.points[0, 0] < 0
    empty = associate([np.zeros((0, 2))] * len(RIG), RIG)
    assert len(empty) == 0 and empty.members.shape == (0, len(RIG))
    with pytest.raises(ValueError, match="7 cameras"):
        associate(uv[:3], RIG)
    with pytest.raises(ValueError, match="tolerances"):
        associate(uv, RIG, tolerances=[np.ones(1)] * len(RIG))
    with pytest.raises(ValueError, match="min_views"):
        AssociationConfig(min_views=1)
