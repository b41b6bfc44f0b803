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
