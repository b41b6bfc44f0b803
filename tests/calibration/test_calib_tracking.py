"""Board tracking in videos: the window search around the previous frame's board, and the
one-threshold-window ChArUco search, find what the whole-image search finds."""

from __future__ import annotations

import numpy as np
from calib_helpers import rendered_view


def test_tracked_detection_matches_whole_image_detection(tmp_path):
    from freipose.calibration.detect_videos import detect_cameras
    from freipose.calibration.tracking import BoardTracker as _Detector
    from freipose.geometry import CameraRig
    from freipose.io.video import FrameSource
    from freipose.synth.board import default_board, write_board_videos
    from freipose.synth.rig import default_rig

    full = default_rig(4, size=(640, 480))
    rig = CameraRig((full[1],), full.metadata)
    board = default_board()
    videos, poses = write_board_videos(tmp_path, rig, board, 40, seed=4, fmt=".mp4", progress=False)
    video = videos[rig[0].name]
    whole, tracker = _Detector(board), _Detector(board)
    ref, tracked = [], []
    with FrameSource(video) as src:
        for i in range(src.num_frames):
            frame = src.read(i)
            ref.append(whole(frame))
            tracked.append(tracker.track(frame))
    ref, tracked = np.array(ref), np.array(tracked)
    assert tracker.windowed >= 10  # the window search served most frames with a board
    assert tracker.fast >= 0.6 * tracker.windowed  # mostly the one-window search
    a, b = np.isfinite(ref[..., 0]), np.isfinite(tracked[..., 0])
    assert a.sum() > 200
    assert (a & ~b).sum() <= 0.01 * a.sum() and not (b & ~a).any()
    both = a & b
    # the same markers seed cornerSubPix from slightly different outlines; OpenCV stops it
    # at 0.1 px steps, so a few corners end up a few hundredths of a pixel apart
    diff = np.linalg.norm(ref[both] - tracked[both], axis=-1)
    assert np.mean(diff < 1e-3) > 0.9 and np.percentile(diff, 99) < 0.1 and diff.max() < 0.3
    err = [_errors(p, poses, board, rig[0]) for p in (ref, tracked)]
    assert np.median(err[1]) <= 1.02 * np.median(err[0])
    # detect_cameras tracks through videos (one process, same chunks)
    (dets,) = detect_cameras([video], board, jobs=1, progress=False)
    np.testing.assert_array_equal(np.isfinite(dets.points[..., 0]), b)
    np.testing.assert_allclose(dets.points[b], tracked[b])


def _errors(points, poses, board, cam):
    """Distances (N,) px of detected points (F, P, 2) from the true corner projections."""
    from freipose.geometry import project

    out = []
    for f, p in enumerate(points):
        m = np.isfinite(p[:, 0])
        X = board.object_points[m] @ poses[f, :3, :3].T + poses[f, :3, 3]
        out.append(np.linalg.norm(p[m] - project(X, cam), axis=1))
    return np.concatenate(out)


class _DropsMarker:
    """A ChArUco detector that loses one marker (and the corners it supports)."""

    def __init__(self, board, marker_id):
        from freipose.calibration.detect import charuco_detector as _charuco_detector
        from freipose.calibration.tracking import CHARUCO_FAST_WINDOW

        w = CHARUCO_FAST_WINDOW
        self.det = _charuco_detector(board, (w, w))
        self.marker_id = marker_id
        self.calls = 0

    def detectBoard(self, gray):
        self.calls += 1
        cc, ci, mc, mi = self.det.detectBoard(gray)
        if mi is None:
            return cc, ci, mc, mi
        keep = np.asarray(mi).reshape(-1) != self.marker_id
        return cc, ci, tuple(c for c, k in zip(mc, keep) if k), np.asarray(mi)[keep]


def test_one_window_search_falls_back_when_an_expected_marker_is_missing():
    from freipose.calibration.tracking import BoardTracker as _Detector

    _rig, board, _poses, frames = rendered_view(1, 60, 3, slice(16))  # whole board in view
    whole = _Detector(board)
    ref = [whole(f) for f in frames]
    assert all(np.isfinite(r[:, 0]).all() for r in ref)
    # a one-window search that always misses marker 0, which is in view in every frame
    tracker = _Detector(board)
    tracker._fast = _DropsMarker(board, 0)
    tracked = [tracker.track(f) for f in frames]
    assert tracker._fast.calls > 0 and tracker.fast == 0  # never trusted: the marker is missing
    assert tracker.windowed == len(frames) - 1  # the two-window search in the window served
    for r, t in zip(ref, tracked):
        np.testing.assert_array_equal(np.isfinite(r[:, 0]), np.isfinite(t[:, 0]))
    # the real one-window search serves most of these frames
    honest = _Detector(board)
    tracked = [honest.track(f) for f in frames]
    assert honest.fast >= len(frames) // 2
