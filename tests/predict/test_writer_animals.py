"""The incremental poses writer with an animal axis: rows per animal, resumable."""

from __future__ import annotations

import numpy as np
import pytest

from freipose.io.poses import read_poses_h5, run_state
from freipose.predict.estimator import Estimate
from freipose.predict.writer import IncrementalPosesWriter, OutputHeader, partial_path
from freipose.testing import make_circle_rig

KPS = ("nose", "tail")


def _est(rng: np.random.Generator, B: int, C: int) -> Estimate:
    K = len(KPS)
    return Estimate(
        rng.normal(size=(B, K, 3)) * 100, rng.uniform(size=(B, K)),
        rng.normal(size=(B, C, K, 2)) * 50, rng.uniform(size=(B, C, K)),
        np.tile([0.0, 0.0, 50.0, 50.0], (B, C, 1)), rng.normal(size=(B, 3)),
    )  # fmt: skip


def _header(rig, individuals=("m1", "m2")) -> OutputHeader:
    return OutputHeader(KPS, rig, 100, 110, 30.0, individuals=individuals)


def test_writer_with_animal_axis_writes_and_resumes(tmp_path):
    rig = make_circle_rig(3)
    rng = np.random.default_rng(0)
    path = tmp_path / "pair.poses.h5"
    batches = [[_est(rng, 4, 3) for _ in range(2)] for _ in range(3)]  # 12 rows > 10
    ident = np.full((4, 2), 0.75)
    w = IncrementalPosesWriter(path, _header(rig), chunk_rows=4)
    assert w.open() == 0
    w.add_animals([e for e in batches[0]], np.zeros(4), np.ones((4, 3), bool), ident)
    with pytest.raises(ValueError, match="add_animals"):
        w.add(batches[1][0], np.zeros(4), np.ones((4, 3), bool))
    w.close()  # killed after the first chunk
    assert run_state(partial_path(path)).done == 4
    w = IncrementalPosesWriter(path, _header(rig), chunk_rows=4)
    assert w.open() == 4  # resumed
    w.add_animals(batches[1], np.zeros(4), np.ones((4, 3), bool), ident)
    last = [Estimate(*(getattr(e, f)[:2] for f in ("poses", "confidence", "points2d",
                                                   "confidence2d", "boxes", "center")))
            for e in batches[2]]  # fmt: skip
    w.add_animals(last, np.zeros(2), np.ones((2, 3), bool))
    w.finish()
    d = read_poses_h5(path)
    assert d.individuals == ("m1", "m2") and d.poses.shape == (10, 2, 2, 3)
    np.testing.assert_allclose(d.poses[4:8, 1], batches[1][1].poses)
    np.testing.assert_allclose(d.extra["points2d"][:4, 0], batches[0][0].points2d)
    assert d.extra["center"].shape == (10, 2, 3) and d.extra["status"].shape == (10,)
    np.testing.assert_allclose(d.identity_confidence[:8], 0.75)
    assert np.isnan(d.identity_confidence[8:]).all()  # not given: unknown
    # another set of animals is another run: the partial file is not resumed
    w = IncrementalPosesWriter(tmp_path / "b.poses.h5", _header(rig), chunk_rows=4)
    w.open()
    w.add_animals(batches[0], np.zeros(4), np.ones((4, 3), bool))
    w.close()
    w = IncrementalPosesWriter(tmp_path / "b.poses.h5", _header(rig, ("x", "y")), chunk_rows=4)
    assert w.open() == 0
    w.close()


def test_shards_with_animal_axis_merge(tmp_path):
    from freipose.predict.merge import merge_shards

    rig = make_circle_rig(2)
    rng = np.random.default_rng(1)
    ests = [_est(rng, 5, 2) for _ in range(2)]
    paths = []
    for i, (a, b) in enumerate(((100, 105), (105, 110))):
        h = OutputHeader(KPS, rig, a, b, 30.0, run_start=100, run_stop=110, shard=(i, 2),
                         up=(0.0, 0.0, 1.0), individuals=("m1", "m2"))  # fmt: skip
        w = IncrementalPosesWriter(tmp_path / f"s.shard-{i}-of-2.poses.h5", h, chunk_rows=5)
        w.open()
        w.add_animals(ests, np.zeros(5), np.ones((5, 2), bool), np.full((5, 2), 0.5 + i / 4))
        paths.append(w.finish())
    d = read_poses_h5(merge_shards(paths, tmp_path / "s.poses.h5"))
    assert d.individuals == ("m1", "m2") and d.poses.shape == (10, 2, 2, 3)
    np.testing.assert_allclose(d.poses[5:, 0], ests[0].poses)
    np.testing.assert_allclose(d.identity_confidence[:, 1], [0.5] * 5 + [0.75] * 5)


def test_reorder_animals_moves_every_per_animal_dataset_and_resumes(tmp_path):
    import h5py

    from freipose.predict.writer import ORDER_PATH

    rig = make_circle_rig(3)
    rng = np.random.default_rng(2)
    ests = [_est(rng, 10, 3) for _ in range(2)]
    ident = np.tile([0.25, 0.75], (10, 1))
    order = np.tile([0, 1], (10, 1))
    order[2:4] = [1, 0]  # animal 0's poses of frames 2-3 are in row 1 (rows 4-7 stay)
    order[8:] = [1, 0]

    def written(path):
        w = IncrementalPosesWriter(path, _header(rig), chunk_rows=4)
        w.open()
        w.add_animals(ests, np.zeros(10), np.ones((10, 3), bool), ident)
        return w

    w = written(tmp_path / "a.poses.h5")
    with pytest.raises(ValueError, match="permutations"):
        w.reorder_animals(np.zeros((10, 2), int))
    w.reorder_animals(order)
    d = read_poses_h5(w.finish())
    rows = np.arange(10)
    for a in range(2):
        src = [ests[k] for k in order[:, a]]
        np.testing.assert_allclose(d.poses[:, a], [e.poses[t] for t, e in zip(rows, src)])
        np.testing.assert_allclose(
            d.extra["points2d"][:, a], [e.points2d[t] for t, e in zip(rows, src)]
        )
        centres = [e.center[t] for t, e in zip(rows, src)]
        np.testing.assert_allclose(d.extra["center"][:, a], centres)
        np.testing.assert_allclose(d.identity_confidence[:, a], ident[rows, order[:, a]])
    flagged = np.asarray(d.extra["identity_flagged"])
    np.testing.assert_array_equal(flagged.any(1), np.isin(rows, [2, 4, 8]))
    np.testing.assert_array_equal(d.extra["identity_order"], order)
    # killed after the first chunk of the reordering: the run started again finishes it
    w = written(tmp_path / "b.poses.h5")
    real = w._out.flush
    calls = []

    def killed(*args, **kwargs):
        calls.append(1)
        real(*args, **kwargs)
        if len(calls) == 2:  # the order stored, the first chunk rewritten
            raise KeyboardInterrupt

    w._out.flush = killed
    with pytest.raises(KeyboardInterrupt):
        w.reorder_animals(order)
    w._out.flush = real
    w.close()
    with h5py.File(partial_path(tmp_path / "b.poses.h5"), "r") as f:
        assert int(f.attrs["reordered_frames"]) == 4 and ORDER_PATH in f
    w = IncrementalPosesWriter(tmp_path / "b.poses.h5", _header(rig), chunk_rows=4)
    assert w.open() == 10
    stored = w.stored_animal_order()
    np.testing.assert_array_equal(stored, order)
    with pytest.raises(ValueError, match="another order"):
        w.reorder_animals(np.tile([0, 1], (10, 1)))
    w.reorder_animals(stored)
    again = read_poses_h5(w.finish())
    np.testing.assert_array_equal(again.poses, d.poses)
    np.testing.assert_array_equal(again.extra["identity_flagged"], d.extra["identity_flagged"])


def test_a_disk_too_full_to_reorder_keeps_the_rows(tmp_path, monkeypatch):
    import freipose.predict.writer as writer
    from freipose.errors import OutputWriteError

    rig = make_circle_rig(2)
    rng = np.random.default_rng(5)
    path = tmp_path / "full.poses.h5"
    w = IncrementalPosesWriter(path, _header(rig), chunk_rows=4)
    w.open()
    w.add_animals([_est(rng, 10, 2) for _ in range(2)], np.zeros(10), np.ones((10, 2), bool))
    before = np.array(w.poses())

    def full(path, needed, what="it takes"):
        raise OutputWriteError(f"no room: {what}")

    monkeypatch.setattr(writer, "check_free_space", full)
    with pytest.raises(OutputWriteError, match="reordered rows"):
        w.reorder_animals(np.tile([1, 0], (10, 1)))
    w.close()
    monkeypatch.undo()
    w = IncrementalPosesWriter(path, _header(rig), chunk_rows=4)
    assert w.open() == 10  # the predictions are kept; the run started again reorders them
    w.reorder_animals(w.stored_animal_order())
    np.testing.assert_array_equal(read_poses_h5(w.finish()).poses, before[:, ::-1])
