"""Several animals: one box per animal per view, and 3D animal hypotheses."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from social_scene import observe, social_scene, true_boxes

from freipose.detect import BackgroundSubtractor, Candidates
from freipose.detect.boxes import box_centers, box_iou
from freipose.detect.multi import (
    AnimalsConfig,
    PeakBoxes,
    SplitForeground,
    _shares,
    detect_animals,
    detect_animals_batch,
    split_blob,
    split_by_seeds,
    without_thin_parts,
)
from freipose.geometry import project
from freipose.synth.rig import default_rig

RIG = default_rig(7, seed=0)
ARENA = np.array([[-300.0, 300], [-300, 300], [0, 200]])  # the arena's volume, mm


def test_split_blob_at_a_narrow_contact_and_side_by_side_by_colour() -> None:
    m = np.zeros((80, 160), np.uint8)
    cv2.ellipse(m, (45, 40), (40, 22), 0, 0, 360, 1, -1)
    cv2.ellipse(m, (118, 44), (40, 22), 10, 0, 360, 1, -1)  # touches the first at a neck
    parts = split_blob(m > 0, 2)
    assert len(parts) == 2
    xs = sorted(np.nonzero(p)[1].mean() for p in parts)
    assert abs(xs[0] - 45) < 6 and abs(xs[1] - 118) < 6
    assert sum(p.sum() for p in parts) == (m > 0).sum()
    # pressed side by side along their length: no neck; the coat colours separate them
    side = np.zeros((70, 200), bool)
    side[5:35, 10:190] = side[35:65, 10:190] = True
    img = np.zeros((70, 200, 3), np.uint8)
    img[5:35] = (230, 230, 230)
    img[35:65] = (40, 50, 60)
    parts = split_blob(side, 2, img)
    ys = sorted(np.nonzero(p)[0].mean() for p in parts)
    assert abs(ys[0] - 19.5) < 3 and abs(ys[1] - 49.5) < 3
    assert len(split_blob(side, 1)) == 1


def test_thin_parts_such_as_tails_are_removed_and_bodies_kept() -> None:
    m = np.zeros((80, 200), np.uint8)
    cv2.ellipse(m, (60, 40), (40, 18), 0, 0, 360, 255, -1)
    cv2.line(m, (100, 40), (190, 60), 255, 2)  # a tail, 2-3 px wide
    out = without_thin_parts(m, 0.3)
    xs = np.nonzero(out)[1]
    assert xs.max() <= 101 and xs.min() <= 21  # the tail is gone, the body's ends kept
    assert np.count_nonzero(out) >= 0.95 * np.count_nonzero(m[:, :100])
    np.testing.assert_array_equal(without_thin_parts(m, 0.0), m)
    thin_only = np.zeros((40, 40), np.uint8)
    thin_only[20, 5:35] = 255  # nothing but thin parts: kept as it is
    np.testing.assert_array_equal(without_thin_parts(thin_only, 0.3), thin_only)


def test_shares_split_only_blobs_holding_several_animals() -> None:
    assert list(_shares(np.array([2000.0]), 2)) == [2]
    assert list(_shares(np.array([2000.0, 1000]), 3)) == [2, 1]
    assert list(_shares(np.array([1000.0, 950]), 3)) == [1, 1]  # the third one is hidden
    assert list(_shares(np.array([1000.0, 600]), 3)) == [1, 1]  # partly hidden, not two
    assert list(_shares(np.zeros(0), 2)) == []


def _render(scene, frames: list[int]) -> tuple[list[list[np.ndarray]], list[np.ndarray]]:
    """Flat-coloured elliptic animals over a textured background, per frame and view."""
    rng = np.random.default_rng(0)
    w, h = RIG[0].size
    bgs = [cv2.GaussianBlur(rng.integers(60, 140, (h, w, 3), dtype=np.uint8), (9, 9), 3)
           for _ in RIG]  # fmt: skip
    tb = true_boxes(scene, RIG, margin=0.0)
    out = []
    for t in frames:
        views = []
        for c in range(len(RIG)):
            img = bgs[c].copy()
            depth = [
                np.linalg.norm(scene.centres[t, a] - RIG[c].center) for a in range(tb.shape[2])
            ]
            for a in np.argsort(depth)[::-1]:  # far first: the near animal occludes
                uv = project(scene.keypoints[t, a], RIG[c])
                tail, nose = uv[-1], uv[0]
                mid = (tail + nose) / 2
                ang = np.degrees(np.arctan2(*(nose - tail)[::-1]))
                ax = max(np.linalg.norm(nose - tail) / 2, 8)
                bx = 0.22 * (tb[t, c, a, 2] - tb[t, c, a, 0] + tb[t, c, a, 3] - tb[t, c, a, 1]) / 2
                col = tuple(int(v) for v in 255 * scene.colours[a])
                cv2.ellipse(img, (round(mid[0]), round(mid[1])), (round(ax), round(max(bx, 6))),
                            ang, 0, 360, col, -1)  # fmt: skip
            views.append(img)
        out.append(views)
    return out, bgs


def test_split_foreground_finds_both_animals_in_contact() -> None:
    scene = social_scene(2, n_frames=300, seed=0)
    d = np.linalg.norm(scene.centres[:, 0] - scene.centres[:, 1], axis=-1)
    frames = list(np.flatnonzero(d < 90)[::12]) + [0, 299]  # in contact, and apart
    images, bgs = _render(scene, frames)
    sub = BackgroundSubtractor(dict(zip(RIG.names, bgs, strict=True)), threshold=25)
    source = SplitForeground(sub, n_animals=2)
    dets = detect_animals_batch(images, RIG, source, AnimalsConfig(min_views=3, max_animals=2))
    found = 0
    for t, det in zip(frames, dets, strict=True):
        assert det.boxes.shape == (len(det), len(RIG), 4)
        err = np.linalg.norm(det.centers[:, None] - scene.centres[t][None], axis=-1)  # (H, 2)
        found += int((err.min(0) < 40).sum())
    assert found >= 0.9 * 2 * len(frames), (found, len(frames))
    # apart, every view has one box per animal
    far = source.propose(images[-1], RIG.names)
    assert all(len(c) == 2 for c in far)


def test_blob_split_at_the_animals_expected_centres() -> None:
    side = np.zeros((70, 200), bool)  # pressed side by side: no neck, one coat
    side[5:35, 10:190] = side[35:65, 10:190] = True
    parts = split_by_seeds(side, np.array([[100.0, 50], [100, 20]]))
    assert [round(np.nonzero(p)[0].mean(), 1) for p in parts] == [49.5, 19.5]
    assert sum(p.sum() for p in parts) == side.sum()
    blind = split_blob(side, 2)  # one coat, no neck: the outline alone cuts across both
    assert all(abs(np.nonzero(p)[0].mean() - 34.5) < 3 for p in blind)
    # the source: with the centres of two animals in contact, per view the blob is split
    # between them; the foreground masks are the image's size
    scene = social_scene(2, n_frames=300, seed=0)
    d = np.linalg.norm(scene.centres[:, 0] - scene.centres[:, 1], axis=-1)
    t = int(np.argmin(d))
    images, bgs = _render(scene, [t])
    sub = BackgroundSubtractor(dict(zip(RIG.names, bgs, strict=True)), threshold=25)
    source = SplitForeground(sub, n_animals=2)
    uv = np.stack([project(scene.centres[t], cam) for cam in RIG])  # (C, 2, 2)
    seeded = source.propose_seeded(images[0], RIG.names, list(uv))
    tb = true_boxes(scene, RIG)[t]  # (C, A, 4)
    plain = source.propose(images[0], RIG.names)
    hits = [[(box_iou(c.boxes[:, None], tb[v][None]) >= 0.5).any(0).sum() for v, c in
             enumerate(found)] for found in (plain, seeded)]  # fmt: skip
    assert sum(hits[1]) >= sum(hits[0]) and sum(hits[1]) >= 0.75 * 2 * len(RIG), hits
    masks = source.foreground_masks(images[0], RIG.names)
    assert masks[0].shape == images[0][0].shape[:2] and masks[0].dtype == bool
    with pytest.raises(ValueError, match="seed arrays"):
        source.propose_seeded(images[0], RIG.names, list(uv)[:2])


def test_detect_animals_on_simulated_boxes() -> None:
    """Recall per animal, shared boxes where two animals are one blob, replacements where hidden."""
    scene = social_scene(3, n_frames=120, seed=2)
    obs = observe(scene, RIG, seed=3, p_drop=0.1, p_false=0.3, hidden={(1, 4): (0, 119)})
    tb = true_boxes(scene, RIG)
    hits = total = shared = 0
    for t in range(120):
        cands = [Candidates(b, np.ones(len(b))) for b in obs.boxes[t]]
        det = detect_animals(cands, RIG, AnimalsConfig(min_views=3), bounds=ARENA)
        assert np.isfinite(det.boxes).all() and np.isfinite(det.crop_boxes).all()
        err = np.linalg.norm(det.centers[:, None] - scene.centres[t][None], axis=-1)
        for a in range(3):
            total += 1
            if not len(det) or err[:, a].min() > 40:
                continue
            hits += 1
            h = int(np.argmin(err[:, a]))
            # the hidden view gets a box around the animal all the same
            assert box_iou(det.boxes[h, 4], tb[t, 4, a]) > 0.3 or det.shared[h, 4]
            shared += int(det.shared[h].sum())
            assert (det.scores[h][~det.own[h] & ~det.shared[h]] == 0).all()
        assert sum(len(x) for x in det.leftover) >= sum((obs.truth[t][c] == -1).sum()
                                                        for c in range(7)) - 1  # fmt: skip
    assert hits >= 0.98 * total
    assert shared > 0  # merged boxes in the contact frames are shared by both animals


def test_peak_boxes_and_bad_input() -> None:
    class Fake:
        def propose(self, images, cameras):
            b = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [50, 50, 60, 60], [80, 80, 90, 90]])
            return [Candidates(b, np.array([0.9, 0.8, 0.5, 0.05])) for _ in images]

    out = PeakBoxes(Fake(), max_boxes=3, min_score=0.1, iou_threshold=0.5).propose([None], ["c"])
    np.testing.assert_allclose(box_centers(out[0].boxes), [[5, 5], [55, 55]])
    with pytest.raises(ValueError, match="max_boxes"):
        PeakBoxes(Fake(), max_boxes=0)
    with pytest.raises(ValueError, match="7 cameras"):
        detect_animals([Candidates.empty()] * 3, RIG)
    with pytest.raises(ValueError, match="min_views"):
        AnimalsConfig(min_views=1)
    empty = detect_animals([Candidates.empty()] * 7, RIG)
    assert len(empty) == 0 and empty.boxes.shape == (0, 7, 4)
