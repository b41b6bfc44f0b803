"""The detector's training views: every labeled animal's box, several animals per view."""

from __future__ import annotations

import numpy as np

from freipose.detect.boxes import boxes_from_points
from freipose.detect.train import DetectorTrainConfig
from freipose.detect.train_views import collect_views, stack_boxes
from freipose.synth.rig import default_rig

RIG = default_rig(2, seed=0)


def _sample(own: np.ndarray, others: np.ndarray | None) -> dict:
    s = {
        "rig": RIG,
        "images": [np.zeros((int(c.size[1]), int(c.size[0]), 3), np.uint8) for c in RIG],
        "points2d": np.full((len(RIG), len(own), 2), np.nan),
        "points3d": own,
    }
    if others is not None:
        s["others3d"] = others
    return s


def test_views_carry_the_other_animals_boxes() -> None:
    rng = np.random.default_rng(0)
    own = rng.normal([-80, 0, 40], 15, (12, 3))
    other = rng.normal([90, 30, 40], 15, (1, 12, 3))
    cfg = DetectorTrainConfig(input_size=128)
    views = collect_views([_sample(own, other)], [0], cfg)
    assert views.boxes.shape == (len(RIG), 2, 4)
    sc = 128 / max(RIG[0].size)
    want = boxes_from_points(RIG.project(other[0])[0], margin=cfg.box_margin)
    np.testing.assert_allclose(views.boxes[0, 1], (want + 0.5) * sc - 0.5, atol=1e-6)
    # one animal per instant: one box per view, as before
    alone = collect_views([_sample(own, None)], [0], cfg)
    assert alone.boxes.shape == (len(RIG), 4)
    np.testing.assert_allclose(alone.boxes, views.boxes[:, 0])


def test_boxes_of_different_counts_are_padded() -> None:
    out = stack_boxes([np.ones(4), np.ones((2, 4)), np.ones((1, 4))])
    assert out.shape == (3, 2, 4)
    assert np.isnan(out[0, 1]).all() and np.isnan(out[2, 1]).all() and (out[1] == 1).all()
    assert stack_boxes([np.ones(4), np.ones((1, 4))]).shape == (2, 4)


class _TwoAnimals:
    """A box source that sees both animals: the other one first (the better score)."""

    def __init__(self, boxes: np.ndarray):
        self.boxes = boxes  # (C, 2, 4): this animal, the other

    def propose(self, images, cameras):
        from freipose.detect.base import Candidates

        return [Candidates(self.boxes[c, ::-1], np.array([0.9, 0.8])) for c in range(len(images))]


def test_evaluation_among_several_animals_finds_this_one() -> None:
    """Labels of several animals: a view counts where any box covers the animal, and the
    3D centre is that of the hypothesis nearest it (not the best-scored other animal)."""
    from freipose.detect.evaluate import evaluate_source

    rig = default_rig(4, seed=0)
    rng = np.random.default_rng(1)
    own = rng.normal([-90, 0, 40], 12, (12, 3))
    other = rng.normal([100, 40, 40], 12, (1, 12, 3))
    sample = {
        "rig": rig,
        "images": [np.zeros((int(c.size[1]), int(c.size[0]), 3), np.uint8) for c in rig],
        "points2d": np.full((len(rig), 12, 2), np.nan),
        "points3d": own,
        "camera_names": list(rig.names),
        "others3d": other,
    }
    boxes = np.stack([boxes_from_points(rig.project(own), margin=0.1),
                      boxes_from_points(rig.project(other[0]), margin=0.1)], axis=1)  # fmt: skip
    m = evaluate_source(_TwoAnimals(boxes), [sample])
    assert m.recall == 1.0 and m.recall_top1 == 0.0  # the best box is the other animal
    assert m.median_center_error < 5.0 and m.center_rate == 1.0
