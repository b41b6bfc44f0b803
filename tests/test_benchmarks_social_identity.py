"""benchmarks/social_identity.py: identity switches of whole poses, and the tracks' order."""

from __future__ import annotations

import numpy as np

BENCHMARK = "social_identity"  # the script the conftest fixture ``bench`` loads


def _truth(n: int) -> np.ndarray:
    """(n, 2, 3, 3) two 3-keypoint animals walking 150 mm apart."""
    body = np.array([[0.0, 0, 40], [50, 0, 40], [100, 0, 30]])
    walk = np.arange(n)[:, None] * [5.0, 0, 0]
    return np.stack([walk[:, None] + body, walk[:, None] + body + [0, 150, 0]], 1)


def test_pose_identity_counts_strays_and_swaps(bench):
    truth = _truth(40)
    assert bench.pose_identity(truth, truth, 10.0)["switches"] == 0
    stray = truth.copy()
    stray[10:12] = stray[10:12, ::-1]  # exchanged for two frames and back: 2 per animal
    got = bench.pose_identity(stray, truth, 10.0)
    assert got["switches"] == 4 and got["lasting_switches"] == 0
    assert np.isclose(got["identity_accuracy"], 38 / 40)
    flagged = np.zeros((40, 2), bool)
    flagged[30, 0] = True  # a flag long after the stray finds none of its switches
    assert bench.pose_identity(stray, truth, 10.0, flagged)["switches_flagged"] == 0
    flagged[9, 0] = True  # one frame before it: all four
    got = bench.pose_identity(stray, truth, 10.0, flagged)
    assert got["switches_flagged"] == 4 and np.isclose(got["flagged_fraction"], 2 / 80)
    swap = truth.copy()
    swap[20:] = swap[20:, ::-1]  # exchanged for good
    got = bench.pose_identity(swap, truth, 10.0)
    assert got["switches"] == 2 and got["lasting_switches"] == 2
    between = truth.copy()
    between[5, 0] = 0.5 * (truth[5, 0] + truth[5, 1])  # halfway: no match, not a switch
    got = bench.pose_identity(between, truth, 10.0)
    assert got["switches"] == 0 and got["matched"] < 1


def test_score_undoes_the_stored_order(bench, tmp_path):
    import h5py

    from freipose.io.animals import stack_animals
    from freipose.io.poses import PoseData, write_poses_h5

    truth = _truth(30)
    written = truth.copy()
    order = np.tile([0, 1], (30, 1))
    order[8:10] = [1, 0]  # the pass gave frames 8-9 back to their animals
    tracks = np.take_along_axis(truth, order[:, :, None, None], 1)  # what the cubes gave

    def save(poses: np.ndarray, path):
        per = {
            f"animal_{a}": PoseData(poses[:, a].astype(np.float32), np.ones((30, 3), np.float32),
                                    ("nose", "back", "tail"), np.arange(30), 10.0)
            for a in range(2)
        }  # fmt: skip
        write_poses_h5(stack_animals(per), path)
        return path

    pred = save(written, tmp_path / "p.poses.h5")
    with h5py.File(pred, "a") as f:
        f["extra/identity_order"] = order.astype(np.int8)
    got = bench.score(pred, save(truth, tmp_path / "t.poses.h5"))
    assert got["switches"] == 0 and got["relabelled_frames"] == 2
    assert got["tracks_order"]["switches"] == 4  # the cubes' poses strayed for 2 frames
    assert np.allclose(got["jpe_mm"], 0) and np.isclose(got["minutes"], 0.05)
    assert not np.allclose(tracks, truth)
