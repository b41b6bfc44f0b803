"""Fixed boxes from the labels and the automatic choice of the box source.

A resting animal (discs that never move) is part of the median background, so background
subtraction cannot find it; the labels' boxes still can. A moving one is found by
background subtraction, which is then chosen.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.detect.auto import auto_box_source, choose_box_source
from freipose.detect.fallback import FallbackBoxesError, FixedBoxes
from freipose.detect.label_boxes import label_boxes
from freipose.detect.multiview import ConsistencyConfig, detect_multiview_batch
from freipose.io.calibration_toml import write_calibration_toml
from freipose.io.labels import LabelSet, SessionInfo, write_labels_h5
from freipose.io.session import discover_sessions
from freipose.io.video import FrameSource, VideoWriter
from freipose.testing import make_circle_rig

BODY = np.array([[40.0, 0, 25], [15, 15, 30], [15, -15, 30], [-45, 0, 15], [0, 0, 45]])
N = 30


def _scene(tmp_path, moving: bool):
    """Session folder with 3 videos of the animal, and its labels (every 3rd frame)."""
    rig = make_circle_rig(3, radius=600, height=400, size=(120, 90), focal=110)
    step = np.array([8.0, -5.0, 0.0]) if moving else np.zeros(3)
    X = BODY[None] + np.arange(N)[:, None, None] * step + np.array([-100.0, 60.0, 0.0]) * moving
    rng = np.random.default_rng(0)
    sess = tmp_path / ("moving" if moving else "resting")
    bgs = [np.clip(rng.normal(90, 6, (90, 120, 3)), 0, 255).astype(np.uint8) for _ in rig]
    for c, cam in enumerate(rig):
        with VideoWriter(sess / f"{cam.name}.mkv", 25, (120, 90)) as w:
            for t in range(N):
                img = bgs[c].copy()
                for u, v in rig.subset([cam.name]).project(X[t])[0]:
                    cv2.circle(img, (int(round(u)), int(round(v))), 4, (230, 230, 230), -1)
                w.write(img)
    write_calibration_toml(rig, sess / "calibration.toml")
    fi = np.arange(0, N, 3)
    labels = LabelSet(
        np.array([sess.name] * len(fi), dtype=object), fi,
        np.moveaxis(rig.project(X[fi]), 0, 0), X[fi], tuple(rig.names),
        tuple(f"k{i}" for i in range(len(BODY))), {sess.name: SessionInfo(rig, {}, 25.0)},
    )  # fmt: skip
    return rig, sess, labels, X


def _sources(rig, sess):
    return {c: FrameSource(sess / f"{c}.mkv") for c in rig.names}


def test_label_boxes_hold_the_animal_and_agree(tmp_path):
    rig, sess, labels, X = _scene(tmp_path, moving=True)
    res = label_boxes(labels, rig, margin=0.1)
    assert set(res.boxes) == set(rig.names) and res.instants == len(labels)
    uv = rig.project(labels.points3d)  # (n, C, K, 2)
    for c, cam in enumerate(rig.names):
        x0, y0, x1, y1 = res.boxes[cam]
        pts = uv[:, c].reshape(-1, 2)
        inside = (pts[:, 0] >= x0) & (pts[:, 0] <= x1) & (pts[:, 1] >= y0) & (pts[:, 1] <= y1)
        on_image = (pts >= -0.5).all(1) & (pts[:, 0] <= 119.5) & (pts[:, 1] <= 89.5)
        assert inside[on_image].all()
    imgs = [[np.zeros((90, 120, 3), np.uint8)] * 3]
    det = detect_multiview_batch(imgs, rig, res.source(), ConsistencyConfig())[0]
    assert det.n_agree == 3  # the boxes agree on one 3D point: the labels' median centre
    np.testing.assert_allclose(det.center, res.center, atol=5.0)
    empty = labels.select([0])
    nan3d = np.full_like(empty.points3d, np.nan)
    empty = LabelSet(
        empty.session, empty.frame_index, empty.points2d, nan3d, empty.cameras, empty.keypoints
    )
    with pytest.raises(FallbackBoxesError, match="--calibration"):
        label_boxes(empty, rig)


def test_resting_animal_gets_fixed_boxes_moving_gets_bgsub(tmp_path, caplog):
    rig, sess, labels, X = _scene(tmp_path, moving=False)
    srcs = _sources(rig, sess)
    with caplog.at_level(logging.INFO, logger="freipose.detect.auto"):
        got = choose_box_source(rig, srcs, range(N), labels=labels, probe=10, bg_samples=15)
    assert got.method == "fixed" and isinstance(got.source, FixedBoxes)
    assert "using fixed boxes from the labels: no detector given (--detector)" in caplog.text
    assert "background subtraction found the animal in 0 of 10 sampled frames" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="freipose.detect.auto"):
        none = choose_box_source(rig, srcs, range(N), labels=None, probe=10, bg_samples=15)
    assert none.method == "bgsub" and "--fixed-boxes" in caplog.text
    rig2, sess2, labels2, _ = _scene(tmp_path, moving=True)
    got2 = choose_box_source(rig2, _sources(rig2, sess2), range(N), labels=labels2, probe=10)
    assert got2.method == "bgsub", got2.reason
    assert "background subtraction found the animal in" in got2.reason


def test_auto_for_a_session_and_the_labels_boxes_command(tmp_path):
    rig, sess, labels, X = _scene(tmp_path, moving=False)
    write_labels_h5(labels, tmp_path / "train.h5")
    (session,) = discover_sessions([sess], None)
    got = auto_box_source(session, (0, N), None, tmp_path / "train.h5", bg_samples=15)
    assert got.method == "fixed"
    res = CliRunner().invoke(
        cli, ["labels", "boxes", str(tmp_path / "train.h5"), "-o", str(tmp_path / "b.toml")]
    )
    assert res.exit_code == 0, res.output
    fb = FixedBoxes.from_toml(tmp_path / "b.toml")
    assert set(fb.boxes) == set(rig.names)
    for cam in rig.names:
        np.testing.assert_allclose(fb.boxes[cam], got.source.boxes[cam], atol=0.06)


def test_2d_labels_of_another_rig_do_not_count(tmp_path):
    rig, sess, labels, X = _scene(tmp_path, moving=True)
    far = labels.points2d.copy()
    far[0, :, 0] = [1.0, 1.0]  # a 2D label at the image corner, in every camera
    other = make_circle_rig(3, radius=650, height=420, size=(120, 90), focal=110)
    mk = lambda r: LabelSet(  # noqa: E731
        labels.session, labels.frame_index, far, labels.points3d, labels.cameras,
        labels.keypoints, {sess.name: SessionInfo(r, {}, 25.0)},
    )  # fmt: skip
    same = label_boxes(mk(rig), rig).boxes
    assert all(same[c][0] <= 1.0 for c in rig.names)  # this rig's own 2D labels count
    foreign = label_boxes(mk(other), rig).boxes  # another rig's: only projected 3D labels
    assert foreign == label_boxes(
        LabelSet(labels.session, labels.frame_index, np.full_like(far, np.nan),
                 labels.points3d, labels.cameras, labels.keypoints,
                 {sess.name: SessionInfo(other, {}, 25.0)}),
        rig,
    ).boxes  # fmt: skip


def test_labels_of_two_animals_per_frame_give_no_fixed_boxes():
    # two animals in every labeled frame: one cube between them would fit neither
    rig = make_circle_rig(3, radius=600, height=400, size=(120, 90), focal=110)
    X = np.concatenate([BODY[None], BODY[None] + np.array([150.0, 0, 0])])
    labels = LabelSet(
        np.array(["s", "s"], dtype=object), np.array([0, 0]), rig.project(X), X,
        tuple(rig.names), tuple(f"k{i}" for i in range(len(BODY))),
        {"s": SessionInfo(rig, {}, 25.0)},
    )  # fmt: skip
    with pytest.raises(FallbackBoxesError, match="2 animals in one frame"):
        label_boxes(labels, rig)
    assert label_boxes(labels.select([0]), rig).instants == 1


def _black_session(tmp_path, rig):
    sess = tmp_path / "black"
    for cam in rig:
        with VideoWriter(sess / f"{cam.name}.mkv", 25, (120, 90)) as w:
            for _ in range(N):
                w.write(np.zeros((90, 120, 3), np.uint8))
    return sess


def test_black_videos_get_no_boxes_and_a_warning(tmp_path, caplog):
    rig, _, labels, _ = _scene(tmp_path, moving=False)
    srcs = _sources(rig, _black_session(tmp_path, rig))
    with caplog.at_level(logging.WARNING, logger="freipose.detect.auto"):
        got = choose_box_source(rig, srcs, range(N), labels=labels, probe=10, bg_samples=15)
        none = choose_box_source(rig, srcs, range(N), labels=None, probe=10, bg_samples=15)
    assert "blank in every camera" in caplog.text
    black = [[np.zeros((90, 120, 3), np.uint8)] * 3]
    for choice in (got, none):  # the animal is not found: no centre, nothing to crop
        det = detect_multiview_batch(black, rig, choice.source, ConsistencyConfig())[0]
        assert det.n_agree == 0 and not np.isfinite(det.center).any()
    # on frames with content the fixed boxes are still proposed
    lit = [[np.asarray(s.read(0)) for s in _sources(rig, _scene(tmp_path, False)[1]).values()]]
    assert detect_multiview_batch(lit, rig, got.source, ConsistencyConfig())[0].n_agree == 3


def test_blank_images_and_the_wrapper():
    from freipose.detect.fallback import SkipBlank, is_blank

    rng = np.random.default_rng(0)
    assert is_blank(np.zeros((90, 120, 3), np.uint8))
    assert is_blank(np.full((90, 120), 200, np.uint8))
    assert not is_blank(np.clip(rng.normal(90, 6, (90, 120, 3)), 0, 255).astype(np.uint8))
    fixed = FixedBoxes({"a": [10, 10, 50, 50]})
    wrapped = SkipBlank(fixed)
    blank, lit = np.zeros((90, 120, 3), np.uint8), rng.integers(0, 255, (90, 120, 3), np.uint8)
    got = wrapped.propose([blank, lit], ["a", "a"])
    assert len(got[0].boxes) == 0 and len(got[1].boxes) == 1
    assert len(fixed.propose([blank], ["a"])[0].boxes) == 1  # without skip_blank: as given
