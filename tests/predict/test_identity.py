"""The whole-recording identity pass: swaps of the frame-by-frame tracker undone, nothing else."""

from __future__ import annotations

import numpy as np
import pytest

from freipose.predict.identity import resolve_identities, track_features
from freipose.predict.tracking import identity_switches

COATS = np.array([[0.9, 0.9, 0.85], [0.3, 0.25, 0.2], [0.8, 0.3, 0.1]])


def _side_by_side(n: int, rng: np.random.Generator, gap: float = 80.0, animals: int = 2):
    """Animals walking together ``gap`` mm apart (in contact), the third far away."""
    walk = np.cumsum(rng.normal(0, 4, (n, 3)) * [1, 1, 0], 0) + [0, 0, 40]
    out = [walk + [0, k * gap, 0] for k in range(min(animals, 2))]
    if animals == 3:
        out.append(walk + [0, -400, 0])
    return np.stack(out, 1)


def _tracked(truth: np.ndarray, rng: np.random.Generator, swaps: dict[int, tuple[int, int]],
             coats: np.ndarray = COATS, hidden: range = range(0)):  # fmt: skip
    """Tracks that exchange animals at the given frames, with the hypotheses' coat features.

    Hypothesis ``a`` of a frame is animal ``a`` (noisy centre and coat); track ``i`` follows
    animal ``carry[i]``, and ``swaps[t] = (i, j)`` exchanges what tracks i and j follow from
    frame t on. During ``hidden`` the second track is unmatched (a blob of two animals).
    """
    t_n, a_n = truth.shape[:2]
    carry = np.arange(a_n)
    centers = np.full((t_n, a_n, 3), np.nan)
    hyp = np.full((t_n, a_n), -1, dtype=np.int64)
    feats = []
    for t in range(t_n):
        if t in swaps:
            i, j = swaps[t]
            carry[[i, j]] = carry[[j, i]]
        x = truth[t] + rng.normal(0, 3, (a_n, 3))
        feats.append(coats[:a_n] + rng.normal(0, 0.05, (a_n, 3)))
        for i in range(a_n):
            if i == 1 and t in hidden:
                continue
            centers[t, i], hyp[t, i] = x[carry[i]], carry[i]
    return centers, hyp, feats


def _apply(order: np.ndarray, centers: np.ndarray) -> np.ndarray:
    return centers[np.arange(len(order))[:, None], order]


def test_a_swap_in_contact_is_undone_at_its_frame() -> None:
    for seed in range(4):
        rng = np.random.default_rng(seed)
        truth = _side_by_side(200, rng)
        # the frame-by-frame tracker exchanged the animals in a blob of both (frames 55-64)
        centers, hyp, feats = _tracked(truth, rng, {60: (0, 1)}, hidden=range(55, 65))
        assert identity_switches(centers, truth)[0] >= 1
        res = resolve_identities(centers, hyp, feats)
        assert identity_switches(_apply(res.order, centers), truth)[0] == 0
        assert res.changes == 1 and res.corrected[60].all() and res.corrected.sum() == 2
        assert res.separation > 5  # two clearly different coats


def test_coats_decide_where_motion_cannot() -> None:
    rng = np.random.default_rng(7)
    truth = _side_by_side(200, rng)
    # both tracks lose their animals in the blob and come back exchanged: no jump to see
    centers, hyp, feats = _tracked(truth, rng, {60: (0, 1)}, hidden=range(50, 70))
    centers[50:70, 0] = np.nan
    hyp[50:70, 0] = -1
    blind = resolve_identities(centers, hyp, None)
    assert blind.changes == 0  # motion alone has no reason to exchange them ...
    # ... nor against it: after the blob, exchanging costs the exchange alone (2 x 2.0)
    np.testing.assert_allclose(blind.margin[75:], 4.0, atol=1e-6)
    res = resolve_identities(centers, hyp, feats)
    assert identity_switches(_apply(res.order, centers), truth)[0] == 0
    assert res.changes == 1
    assert (res.margin[75:] > 20).all()  # the coats tell them apart


def test_tracks_apart_and_tracks_without_a_swap_are_left_alone() -> None:
    for seed in range(4):
        rng = np.random.default_rng(10 + seed)
        truth = _side_by_side(150, rng, gap=400.0)  # never in contact
        centers, hyp, feats = _tracked(truth, rng, {70: (0, 1)})
        res = resolve_identities(centers, hyp, feats)
        np.testing.assert_array_equal(res.order, np.broadcast_to([0, 1], (150, 2)))
        assert np.isinf(res.margin).all()  # no frame where they could be exchanged
        # two animals in contact with the same coat, correctly tracked: nothing to correct
        close = _side_by_side(150, rng)
        same = np.repeat(COATS[:1], 3, 0)
        centers, hyp, feats = _tracked(close, rng, {}, coats=same)
        assert resolve_identities(centers, hyp, feats).changes == 0


def test_three_animals_two_in_contact_exchange() -> None:
    rng = np.random.default_rng(3)
    truth = _side_by_side(200, rng, animals=3)
    centers, hyp, feats = _tracked(truth, rng, {90: (0, 1)}, hidden=range(85, 95))
    res = resolve_identities(centers, hyp, feats)
    assert identity_switches(_apply(res.order, centers), truth)[0] == 0
    assert (res.order[:, 2] == 2).all()  # the animal far away never changes track


def test_track_features_and_trivial_cases() -> None:
    hyp = np.array([[1, -1], [0, 1]])
    feats = [np.array([[0.0, 1.0], [2.0, 3.0]]), np.array([[4.0, 5.0], [6.0, 7.0]])]
    f = track_features(hyp, feats)
    assert f is not None
    np.testing.assert_array_equal(f[0, 0], [2, 3])
    assert np.isnan(f[0, 1]).all()
    np.testing.assert_array_equal(f[1], [[4, 5], [6, 7]])
    assert track_features(hyp, [np.zeros((0, 2))] * 2) is None
    one = resolve_identities(np.zeros((5, 1, 3)), np.zeros((5, 1), np.int64), None)
    assert one.changes == 0 and (one.order == 0).all()
    empty = resolve_identities(np.full((0, 2, 3), np.nan), np.zeros((0, 2), np.int64), None)
    assert empty.order.shape == (0, 2)


def test_switches_flagged_counts_a_flag_near_a_switch_on_either_track() -> None:
    from freipose.predict.animals import flagged_switches

    assigned = np.array([[0, 1]] * 10 + [[-1, -1]] * 3 + [[1, 0]] * 10)  # both switch at 13
    flagged = np.zeros((23, 2), bool)
    assert flagged_switches(assigned, flagged, 5) == 0
    flagged[6, 1] = True  # 3 frames before the animals were last matched, on track 1
    assert flagged_switches(assigned, flagged, 5) == 2  # both switches involve track 1
    assert flagged_switches(assigned, flagged, 2) == 0
    flagged[:] = False
    flagged[20, 0] = True  # after the switch: not a warning of it
    assert flagged_switches(assigned, flagged, 5) == 0


def _two_walking_poses(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 2, 4, 3) two 4-keypoint bodies (100 mm long) walking 60 mm apart, side by side."""
    body = np.array([[0.0, 0, 40], [40, 0, 40], [70, 0, 40], [100, 0, 30]])
    walk = np.cumsum(rng.normal(0, 5, (n, 3)) * [1, 1, 0], 0)
    return np.stack([walk[:, None] + body, walk[:, None] + body + [0, 60, 0]], 1)


def test_relabel_by_poses_undoes_poses_exchanged_for_a_few_frames() -> None:
    from freipose.predict.identity import relabel_by_poses

    rng = np.random.default_rng(3)
    truth = _two_walking_poses(60, rng)
    poses = truth + rng.normal(0, 2, truth.shape)
    poses[20:23] = poses[20:23, ::-1]  # the two cubes' poses exchanged for 3 frames
    poses[40, 1, :2] = np.nan  # a few keypoints missing
    poses[41:43, 0] = np.nan  # one animal not found for a few frames
    poses[43:46] = poses[43:46, ::-1]  # and exchanged right after: its last pose tells
    res = relabel_by_poses(poses, 10.0)
    expect = np.tile([0, 1], (60, 1))
    expect[20:23] = expect[43:46] = [1, 0]
    np.testing.assert_array_equal(res.order, expect)
    assert res.changes == 4 and res.corrected[[20, 23, 43, 46]].all()
    assert res.corrected.sum() == 8
    fixed = np.take_along_axis(poses, res.order[:, :, None, None], 1)
    np.testing.assert_allclose(fixed[20:23], poses[20:23, ::-1])
    # nothing exchanged: nothing moved, however noisy the poses
    clean = relabel_by_poses(truth + rng.normal(0, 8, truth.shape), 10.0)
    assert clean.changes == 0 and (clean.order == [0, 1]).all()
    # exchanged for longer than a second: the tracker's decision, not a stray; kept
    long = truth.copy()
    long[30:45] = long[30:45, ::-1]
    assert relabel_by_poses(long, 10.0).changes == 0
    assert relabel_by_poses(long, 10.0, longest_s=2.0).changes == 2


def test_relabel_by_poses_keeps_the_rows_where_they_do_not_tell() -> None:
    from freipose.predict.identity import relabel_by_poses

    rng = np.random.default_rng(4)
    poses = _two_walking_poses(30, rng)
    poses[10:] = poses[10:, ::-1]  # a lasting exchange at frame 10 ...
    poses[8:16] = np.nan  # ... while both were lost for long: nothing tells which is which
    res = relabel_by_poses(poses, 10.0)
    assert res.changes == 0  # the rows stay (the tracker's identities decide)
    one = relabel_by_poses(poses[:, :1], 10.0)
    assert one.changes == 0 and one.order.shape == (30, 1)
    empty = relabel_by_poses(np.full((5, 2, 4, 3), np.nan), 10.0)
    assert empty.changes == 0
    with pytest.raises(ValueError, match="T, A, K, 3"):
        relabel_by_poses(poses[0], 10.0)


def test_coincident_poses_flags_one_animal_found_twice() -> None:
    from freipose.predict.identity import coincident_poses

    rng = np.random.default_rng(6)
    poses = _two_walking_poses(4, rng)  # 100 mm bodies, 60 mm apart
    poses[1, 1] = poses[1, 0] + rng.normal(0, 3, (4, 3))  # frame 1: both rows on animal 0
    poses[2, 1, :3] = poses[2, 0, :3] + 2.0  # frame 2: three of four keypoints shared
    poses[3, 1] = np.nan  # frame 3: one row missing
    got = coincident_poses(poses)
    np.testing.assert_array_equal(got, [[False, False], [True, True], [True, True],
                                        [False, False]])  # fmt: skip
    # climbing over each other: one body 40 mm above the other is two animals
    over = _two_walking_poses(1, rng)
    over[0, 1] = over[0, 0] + [0, 0, 40]
    assert not coincident_poses(over).any()
    assert coincident_poses(over, fraction=0.5).all()
    assert coincident_poses(np.zeros((3, 1, 4, 3))).shape == (3, 1)


def test_relabel_by_poses_with_three_animals() -> None:
    from freipose.predict.identity import relabel_by_poses

    rng = np.random.default_rng(7)
    two = _two_walking_poses(40, rng)
    truth = np.concatenate([two, two[:, :1] + [0, -200, 0]], axis=1)  # a third, far away
    poses = truth + rng.normal(0, 2, truth.shape)
    poses[15:17] = poses[15:17][:, [0, 2, 1]]  # rows 1 and 2 exchanged for two frames
    res = relabel_by_poses(poses, 10.0)
    expect = np.tile([0, 1, 2], (40, 1))
    expect[15:17] = [0, 2, 1]
    np.testing.assert_array_equal(res.order, expect)
    assert res.changes == 2 and not res.corrected[:, 0].any()
