"""Identity over time: tracks of several animals through contact, occlusion and false detections."""

from __future__ import annotations

import numpy as np
import pytest
from social_scene import observe, social_scene

from freipose.detect import Candidates
from freipose.detect.multi import AnimalsConfig, detect_animals
from freipose.predict.tracking import (
    TrackingConfig,
    TrackingError,
    colour_features,
    identity_accuracy,
    identity_switches,
    lasting_switches,
    track_animals,
)
from freipose.synth.rig import default_rig

FPS = 30.0
COATS = np.array([[0.9, 0.9, 0.85], [0.3, 0.25, 0.2]])


def _hypotheses(
    truth: np.ndarray,
    rng: np.random.Generator,
    merge_mm: float = 60.0,
    hidden: dict[int, range] | None = None,
    p_false: float = 0.0,
    coats: np.ndarray = COATS,
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per frame the detected centres (noisy, merged in contact, hidden, false) and features."""
    centres, feats = [], []
    for t, X in enumerate(truth):
        keep = [a for a in range(len(X)) if t not in (hidden or {}).get(a, ())]
        pts = [X[a] + rng.normal(0, 3, 3) for a in keep]
        fs = [coats[a] + rng.normal(0, 0.03, 3) for a in keep]
        if len(keep) == 2 and np.linalg.norm(X[keep[0]] - X[keep[1]]) < merge_mm:
            pts = [(pts[0] + pts[1]) / 2]  # one blob: one hypothesis with a mixed look
            fs = [(fs[0] + fs[1]) / 2]
        if rng.random() < p_false:
            pts.append(np.r_[rng.uniform(-300, 300, 2), 40])
            fs.append(rng.uniform(0, 1, 3))
        order = rng.permutation(len(pts))
        centres.append(np.asarray(pts).reshape(-1, 3)[order])
        feats.append(np.asarray(fs).reshape(-1, 3)[order])
    return centres, feats


def _line(p0, p1, n: int) -> np.ndarray:
    return np.linspace(np.r_[p0, 40.0], np.r_[p1, 40.0], n)


def test_passing_close_is_followed_by_motion_alone() -> None:
    truth = np.stack([_line((-250, 0), (250, 0), 90), _line((250, 15), (-250, 15), 90)], 1)
    centres, _ = _hypotheses(truth, np.random.default_rng(0))
    tr = track_animals(centres, 2, FPS)
    switches, assigned = identity_switches(tr.centers, truth)
    assert switches == 0
    assert (assigned[[0, -1]] >= 0).all()
    assert tr.centers.shape == (90, 2, 3) and tr.boxes.shape == (90, 2, 0, 4)


def _meet_and_part() -> np.ndarray:
    """Both come from the sides, stand together for 1 s, then leave up and down."""
    a = np.concatenate([_line((-250, 0), (-20, 0), 40), _line((-20, 0), (-20, 0), 30),
                        _line((-20, 0), (-20, 250), 40)])  # fmt: skip
    b = np.concatenate([_line((250, 0), (20, 0), 40), _line((20, 0), (20, 0), 30),
                        _line((20, 0), (20, -250), 40)])  # fmt: skip
    return np.stack([a, b], 1)


def test_appearance_decides_after_contact_and_ambiguity_is_flagged_without_it() -> None:
    truth = _meet_and_part()
    for seed in range(3):
        centres, feats = _hypotheses(truth, np.random.default_rng(seed))
        first = 70 + next(t for t in range(70, 110) if len(centres[t]) == 2) - 70
        part = slice(first, first + 10)  # the first frames after they part
        with_look = track_animals(centres, 2, FPS, features=feats)
        assert identity_switches(with_look.centers, truth)[0] == 0
        assert not with_look.flagged[part].any()
        blind = track_animals(centres, 2, FPS)
        # motion alone cannot tell who leaves where: the tracker says so
        assert blind.flagged[part].any()
        assert np.nanmin(blind.confidence[part]) < np.nanmin(with_look.confidence[part])


def test_identity_kept_through_full_occlusion_and_false_hypotheses() -> None:
    truth = np.stack([_line((-250, 80), (250, 80), 120), _line((-250, -80), (250, -80), 120)], 1)
    hidden = {1: range(40, 65)}  # seen by no camera for 25 frames
    centres, feats = _hypotheses(truth, np.random.default_rng(4), hidden=hidden, p_false=0.2)
    for f in (None, feats):
        tr = track_animals(centres, 2, FPS, features=f)
        switches, assigned = identity_switches(tr.centers, truth)
        assert switches == 0
        assert (assigned[40:65, 1] == -1).all() and (assigned[66:, 1] >= 0).all()
        # a false hypothesis near the hidden animal's prediction may stand in for a frame
        assert tr.observed[41:65, 1].sum() <= 3


def test_a_lost_track_takes_back_its_animal_seen_far_from_the_prediction() -> None:
    a = _line((-200, 0), (-200, 0), 40)
    b = np.concatenate([_line((200, 0), (200, 0), 10), _line((200, -250), (200, -250), 30)])
    truth = np.stack([a, b], 1)
    centres, feats = _hypotheses(truth, np.random.default_rng(1), hidden={1: range(10, 15)})
    late = track_animals(centres, 2, FPS, features=feats,
                         config=TrackingConfig(reacquire=False))  # fmt: skip
    # 250 mm from its prediction: beyond the gate of a track unseen for 5 frames
    assert (identity_switches(late.centers, truth)[1][15:18, 1] == -1).all()
    back = track_animals(centres, 2, FPS, features=feats)
    switches, assigned = identity_switches(back.centers, truth)
    assert switches == 0 and (assigned[:10] >= 0).all()
    assert assigned[15, 1] == -1 and (assigned[16:, 1] >= 0).all()  # seen twice first


def test_tracks_from_simulated_views_of_three_animals() -> None:
    rig = default_rig(7, seed=0)
    arena = np.array([[-300.0, 300], [-300, 300], [0, 200]])
    scene = social_scene(3, n_frames=150, seed=5)
    obs = observe(scene, rig, seed=6, p_drop=0.15, p_false=0.2)
    dets = []
    for t in range(150):
        cands = [Candidates(b, np.ones(len(b))) for b in obs.boxes[t]]
        dets.append(detect_animals(cands, rig, AnimalsConfig(min_views=3), bounds=arena))
    tr = track_animals([d.centers for d in dets], 3, FPS, boxes=[d.boxes for d in dets])
    switches, assigned = identity_switches(tr.centers, scene.centres)
    assert switches == 0
    assert (assigned >= 0).mean() >= 0.98
    assert tr.boxes.shape == (150, 3, 7, 4)
    h = tr.hypothesis[100, 0]
    np.testing.assert_array_equal(tr.boxes[100, 0], dets[100].boxes[h])


def test_identity_switches_counts_a_swap() -> None:
    truth = np.stack([_line((-200, 0), (200, 0), 20), _line((-200, 200), (200, 200), 20)], 1)
    swapped = truth.copy()
    swapped[10:] = truth[10:, ::-1]
    assert identity_switches(swapped, truth)[0] == 2
    assert identity_switches(truth, truth)[0] == 0


def test_lasting_switches_tell_a_swap_from_a_stray() -> None:
    truth = np.stack([_line((-200, 0), (200, 0), 40), _line((-200, 200), (200, 200), 40)], 1)
    swapped = truth.copy()
    swapped[20:] = truth[20:, ::-1]  # the tracks exchange the animals for good
    strayed = truth.copy()
    strayed[20:23] = truth[20:23, ::-1]  # three frames on the other animal, then back
    strayed[30, 0] = np.nan  # an unmatched frame inside a run does not end it
    n_swap, a_swap = identity_switches(swapped, truth)
    n_stray, a_stray = identity_switches(strayed, truth)
    assert (n_swap, n_stray) == (2, 4)
    assert lasting_switches(a_swap, 5) == 2
    assert lasting_switches(a_stray, 5) == 0
    assert lasting_switches(a_stray, 3) == 4  # strays as long as the threshold count
    assert identity_accuracy(a_swap, 2) == pytest.approx(0.5)
    assert identity_accuracy(a_stray, 2) == pytest.approx(1 - 6 / 79)
    assert np.isnan(identity_accuracy(np.full((5, 2), -1), 2))


def test_colour_features_and_bad_input() -> None:
    img = np.zeros((40, 80, 3), np.uint8)
    img[:, :40] = (0, 0, 255)  # red
    img[:, 40:] = (255, 0, 0)  # blue
    boxes = np.array([[[0, 0, 39, 39], [0, 0, 39, 39]], [[40, 0, 79, 39], [np.nan] * 4]], float)
    f = colour_features([img, img], boxes)
    assert f.shape == (2, 42)
    np.testing.assert_allclose((f**2).sum(1), 1.0)
    assert np.linalg.norm(f[0] - f[1]) > 0.9  # disjoint hue histograms, same brightness
    # black and white coats: no hue, no saturation; told apart by brightness, and only
    # the animal's pixels count where the foreground is given
    floor = np.full((40, 80, 3), 128, np.uint8)
    coats = floor.copy()
    coats[10:30, 5:35] = 10
    coats[10:30, 45:75] = 245
    fg = np.zeros((40, 80), bool)
    fg[10:30, 5:35] = fg[10:30, 45:75] = True
    two = np.array([[[0, 0, 39, 39]], [[40, 0, 79, 39]]], float)
    plain = colour_features([coats], two)
    masked = colour_features([coats], two, masks=[fg])
    assert np.linalg.norm(masked[0] - masked[1]) > 0.95  # disjoint brightness histograms
    assert np.linalg.norm(plain[0] - plain[1]) < np.linalg.norm(masked[0] - masked[1])
    assert np.isnan(colour_features([img, img], boxes, use=np.zeros((2, 2), bool))).all()
    with pytest.raises(TrackingError, match="n_animals"):
        track_animals([np.zeros((1, 3))], 0, FPS)
    with pytest.raises(TrackingError, match="features has 2 frames"):
        track_animals([np.zeros((1, 3))], 1, FPS, features=[np.zeros((1, 3))] * 2)
    with pytest.raises(TrackingError, match="gate_mm"):
        TrackingConfig(gate_mm=0)
    empty = track_animals([np.zeros((0, 3))] * 5, 2, FPS)
    assert not empty.observed.any() and np.isnan(empty.confidence).all()
