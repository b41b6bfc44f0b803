"""Multi-view consistency with synthetic candidate boxes (no images, no network)."""

import numpy as np
import pytest

from freipose.detect import (
    Candidates,
    ConsistencyConfig,
    FixedBoxes,
    consistent_detection,
    consistent_detections,
    detect_multiview,
)
from freipose.detect.boxes import box_centers, box_iou
from freipose.geometry.crops import cube_crop_boxes


def true_boxes(rig, center, size_mm=150.0):
    """Boxes around the projected centre whose size is ``size_mm`` at the camera's depth."""
    uv = rig.project(center[None])[:, 0]
    depth = np.einsum("cij,j->ci", rig.R, center)[:, 2] + rig.t[:, 2]
    half = 0.5 * size_mm * rig.K[:, 0, 0] / depth
    return np.stack([uv[:, 0] - half, uv[:, 1] - half, uv[:, 0] + half, uv[:, 1] + half], -1)


def candidates_from(boxes, scores=None, rng=None, jitter=0.0):
    out = []
    for i, b in enumerate(boxes):
        b = b + (rng.normal(0, jitter, 4) if rng is not None else 0)
        out.append(Candidates(b[None], [0.9 if scores is None else scores[i]]))
    return out


def test_clean_views_agree(circle_rig, rng):
    center = np.array([30.0, -50.0, 60.0])
    boxes = true_boxes(circle_rig, center)
    det = consistent_detection(candidates_from(boxes, rng=rng, jitter=1.0), circle_rig)
    assert det.n_agree == len(circle_rig) and det.agree.all()
    assert np.linalg.norm(det.center - center) < 5.0
    np.testing.assert_allclose(det.crop_boxes, cube_crop_boxes(circle_rig, det.center, 400.0))
    assert np.all(box_iou(det.boxes, boxes) > 0.9)


def test_corrupted_view_does_not_move_centre_and_is_replaced(circle_rig, rng):
    center = np.array([30.0, -50.0, 60.0])
    boxes = true_boxes(circle_rig, center)
    clean = consistent_detection(candidates_from(boxes), circle_rig)
    # View 2's detector points at another object, with a high score; no true box there.
    cands = candidates_from(boxes)
    wrong = boxes[2] + np.array([150.0, 90.0, 150.0, 90.0])
    cands[2] = Candidates(np.stack([wrong, wrong + 60]), [0.99, 0.8])
    det = consistent_detection(cands, circle_rig)
    np.testing.assert_allclose(det.center, clean.center, atol=1e-6)
    assert det.n_agree == len(circle_rig) - 1
    assert not det.agree[2] and det.agree[[0, 1, 3, 4, 5]].all()
    assert det.scores[2] == 0.0  # replacement box
    assert box_iou(det.boxes[2], wrong) == 0.0
    assert box_iou(det.boxes[2], boxes[2]) > 0.8  # the replacement sits on the animal
    np.testing.assert_allclose(
        det.crop_boxes[2], cube_crop_boxes(circle_rig, center, 400.0)[2], atol=1e-6
    )


def test_lower_ranked_true_candidate_is_chosen(circle_rig):
    center = np.array([0.0, 80.0, 40.0])
    boxes = true_boxes(circle_rig, center)
    cands = candidates_from(boxes)
    for v in (1, 4):  # two views: a distractor wins on score, the animal is second
        distractor = boxes[v] + np.array([-120.0, 60, -120, 60])
        cands[v] = Candidates(np.stack([distractor, boxes[v]]), [0.95, 0.4])
    det = consistent_detection(cands, circle_rig)
    assert det.agree.all()
    np.testing.assert_allclose(det.boxes[[1, 4]], boxes[[1, 4]])
    np.testing.assert_allclose(det.scores[[1, 4]], 0.4)
    assert np.linalg.norm(det.center - center) < 1.0


def test_majority_of_wrong_views_with_missing_views(circle_rig):
    center = np.array([10.0, 10.0, 50.0])
    boxes = true_boxes(circle_rig, center)
    cands = candidates_from(boxes)
    cands[0] = Candidates.empty()  # missed
    cands[3] = Candidates.empty()
    det = consistent_detection(cands, circle_rig)
    assert det.n_agree == 4 and not det.agree[0] and not det.agree[3]
    assert np.isfinite(det.boxes).all()  # missed views got replacement boxes
    assert box_iou(det.boxes[0], boxes[0]) > 0.8


def test_no_consensus_gives_nan_centre(circle_rig):
    boxes = true_boxes(circle_rig, np.zeros(3))
    cands = [Candidates.empty() for _ in range(len(circle_rig))]
    cands[0] = Candidates(boxes[0][None], [0.9])
    det = consistent_detection(cands, circle_rig)
    assert det.n_agree == 0 and np.isnan(det.center).all() and np.isnan(det.crop_boxes).all()
    np.testing.assert_allclose(det.boxes[0], boxes[0])  # the view's own best box is kept
    assert np.isnan(det.boxes[1]).all()
    with pytest.raises(ValueError, match="cameras"):
        consistent_detection(cands[:3], circle_rig)
    with pytest.raises(ValueError, match="min_views"):
        ConsistencyConfig(min_views=1)


def test_min_views_and_low_scores(circle_rig):
    center = np.array([0.0, 0.0, 50.0])
    boxes = true_boxes(circle_rig, center)
    cands = [Candidates.empty() for _ in range(len(circle_rig))]
    cands[0], cands[1] = Candidates(boxes[0][None], [0.9]), Candidates(boxes[1][None], [0.9])
    assert consistent_detection(cands, circle_rig).n_agree == 2
    assert consistent_detection(cands, circle_rig, ConsistencyConfig(min_views=3)).n_agree == 0
    cands[1] = Candidates(boxes[1][None], [0.05])  # below min_score
    assert consistent_detection(cands, circle_rig).n_agree == 0


def test_detect_multiview_with_fixed_boxes(circle_rig):
    center = np.array([20.0, 0.0, 30.0])
    boxes = true_boxes(circle_rig, center)
    fixed = FixedBoxes({n: b for n, b in zip(circle_rig.names, boxes)})
    frames = [np.zeros((480, 640, 3), np.uint8)] * len(circle_rig)
    det = detect_multiview(frames, circle_rig, fixed, cube_size=300.0)
    assert det.n_agree == 6
    assert np.linalg.norm(det.center - center) < 1.0
    np.testing.assert_allclose(box_centers(det.crop_boxes), box_centers(boxes), atol=1e-6)
    with pytest.raises(ValueError, match="expected 6 images"):
        detect_multiview(frames[:2], circle_rig, fixed)


def _cluttered(rig, rng, n):
    """n instants: per view 0-3 candidates, most near the animal, some anywhere."""
    out = []
    for _ in range(n):
        uv = rig.project(rng.normal([0, 0, 80], 60, 3)[None])[:, 0]
        cands = []
        for c in range(len(rig)):
            k = int(rng.integers(0, 4))
            near = rng.random(k) < 0.6
            ctr = np.where(near[:, None], uv[c] + rng.normal(0, 6, (k, 2)),
                           rng.uniform(0, 640, (k, 2)))  # fmt: skip
            half = rng.uniform(20, 60, (k, 1))
            scores = np.sort(rng.uniform(0.05, 1, k))[::-1]
            cands.append(Candidates(np.concatenate([ctr - half, ctr + half], 1), scores))
        out.append(cands)
    return out


def test_instants_computed_together_equal_one_by_one(circle_rig, rng):
    """The batched consistency (what detection and prediction run) is the per-instant one."""
    cases = _cluttered(circle_rig, rng, 120)
    cfg = ConsistencyConfig(cube_size=320.0)
    together = consistent_detections(cases, circle_rig, cfg)
    found = 0
    for cands, got in zip(cases, together, strict=True):
        want = consistent_detection(cands, circle_rig, cfg)
        assert (got.agree == want.agree).all() and got.n_agree == want.n_agree
        np.testing.assert_allclose(got.center, want.center, atol=1e-6)
        np.testing.assert_allclose(got.boxes, want.boxes, atol=1e-6)
        np.testing.assert_allclose(got.scores, want.scores)
        np.testing.assert_allclose(got.crop_boxes, want.crop_boxes, atol=1e-6)
        found += bool(np.isfinite(got.center).all())
    assert 20 < found < 120  # both outcomes occur
    assert consistent_detections([], circle_rig, cfg) == []
