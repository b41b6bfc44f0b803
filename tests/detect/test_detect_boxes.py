import numpy as np
import pytest

from freipose.detect.base import Candidates
from freipose.detect.boxes import (
    box_centers,
    box_iou,
    boxes_from_points,
    clip_boxes,
    nms,
    transform_boxes,
    visible_fraction,
)


def test_boxes_from_points_margin_and_missing():
    pts = np.array(
        [[[10.0, 20.0], [30.0, 60.0], [np.nan, np.nan]], [[1, 1], [np.nan, 5], [np.nan] * 2]]
    )
    b = boxes_from_points(pts, margin=0.1)
    # longer side 40 -> 4 px on every side
    np.testing.assert_allclose(b[0], [6, 16, 34, 64])
    assert np.isnan(b[1]).all()  # one finite point only
    with pytest.raises(ValueError, match="shape"):
        boxes_from_points(np.zeros((3, 3)))


def test_iou_and_centres():
    a = np.array([0.0, 0, 10, 10])
    assert box_iou(a, a) == pytest.approx(1.0)
    assert box_iou(a, [5.0, 0, 15, 10]) == pytest.approx(50 / 150)
    assert box_iou(a, [20.0, 20, 30, 30]) == 0.0
    assert np.isnan(box_iou(a, np.full(4, np.nan)))
    np.testing.assert_allclose(box_centers(a), [5, 5])


def test_clip_and_visible_fraction():
    b = np.array([-10.5, -0.5, 9.5, 9.5])  # half outside on the left
    assert visible_fraction(b, (100, 100)) == pytest.approx(0.5)
    np.testing.assert_allclose(clip_boxes(b, (100, 100)), [-0.5, -0.5, 9.5, 9.5])
    assert visible_fraction([200.0, 200, 210, 210], (100, 100)) == 0.0


def test_transform_boxes_flip_and_scale():
    A = np.array([[-2.0, 0, 99], [0, 2, 1]])
    b = transform_boxes(np.array([10.0, 20, 30, 40]), A)
    np.testing.assert_allclose(b, [99 - 60, 41, 99 - 20, 81])


def test_nms_and_candidates_sorted():
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [50, 50, 60, 60.0]])
    keep = nms(boxes, np.array([0.5, 0.9, 0.4]), 0.5)
    assert list(keep) == [1, 2]
    c = Candidates(boxes, [0.1, 0.9, 0.5])
    np.testing.assert_allclose(c.scores, [0.9, 0.5, 0.1])
    np.testing.assert_allclose(c.boxes[0], boxes[1])
    assert len(c.top(2)) == 2 and len(Candidates.empty()) == 0
    with pytest.raises(ValueError, match="scores"):
        Candidates(boxes, [1.0])
