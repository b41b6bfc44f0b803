"""A board at rest over several frames counts as one view (calibration.static_frames)."""

from __future__ import annotations

import numpy as np
from calib_helpers import board_detections

from freipose.calibration.boards import CharucoBoard
from freipose.calibration.detect import CameraDetections
from freipose.calibration.options import CalibrationOptions
from freipose.calibration.pipeline import calibrate_detections
from freipose.calibration.static_frames import merge_static_runs
from freipose.testing import make_circle_rig

BOARD = CharucoBoard(8, 6, 40.0, 30.0, "DICT_4X4_50")


def _with_rest(dets, frame: int, copies: int, bias: np.ndarray, jitter: float, seed: int = 0):
    """The detections with ``frame`` shown ``copies`` times (the same bias, small noise)."""
    rng = np.random.default_rng(seed)
    out = []
    for d in dets:
        view = d.points[frame] + bias
        rest = np.repeat(view[None], copies, axis=0)
        rest = rest + rng.normal(0, jitter, rest.shape)
        pts = np.concatenate([d.points[: frame + 1], rest, d.points[frame + 1 :]])
        pts[frame] = view
        out.append(CameraDetections(d.name, d.size, pts))
    return out


def test_runs_of_still_frames_are_merged_into_one():
    rig = make_circle_rig(3, radius=700.0, height=400.0)
    dets = board_detections(rig, BOARD.object_points, BOARD.size_mm, 20, noise_px=0.2)[0]
    seen = int(np.argmax(sum(d.counts for d in dets)))
    rest = _with_rest(dets, seen, 5, np.zeros(2), jitter=0.02)
    merged = merge_static_runs(rest)
    assert merged.runs == ((seen, seen + 5, seen),) and merged.frames_merged == 5
    for a, b in zip(rest, merged.detections):
        assert not b.mask[seen + 1 : seen + 6].any()
        np.testing.assert_allclose(b.points[seen], a.points[seen : seen + 6].mean(axis=0))
        np.testing.assert_array_equal(b.points[:seen], a.points[:seen])
    # the frame to keep (the origin frame) holds the run's corners
    assert merge_static_runs(rest, keep=seen + 3).runs == ((seen, seen + 5, seen + 3),)
    assert not merge_static_runs(dets).runs  # a moving board: nothing merged


def test_a_board_at_rest_weighs_as_one_view():
    rig = make_circle_rig(4, radius=700.0, height=400.0, distortion=True)
    dets = board_detections(rig, BOARD.object_points, BOARD.size_mm, 60, noise_px=0.2)[0]
    seen = int(np.argmax(sum(d.counts for d in dets)))
    bias = np.array([0.25, -0.2])  # the corner refinement's error for this one pose
    opts = CalibrationOptions(jobs=1, progress=False, dist_model="k1k2")
    once = calibrate_detections(_with_rest(dets, seen, 0, bias, 0.0), BOARD, opts)
    rest = calibrate_detections(_with_rest(dets, seen, 12, bias, 0.0), BOARD, opts)
    for a, b in zip(once.rig, rest.rig):
        np.testing.assert_allclose(b.K, a.K, rtol=0, atol=1e-6)
        np.testing.assert_allclose(b.center, a.center, rtol=0, atol=1e-6)
