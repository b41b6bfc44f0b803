"""Board tracking in videos: the window search around the previous frame's board finds what
the whole-image search finds."""

from __future__ import annotations

import numpy as np


def test_tracked_detection_matches_whole_image_detection(tmp_path):
    from freipose.calibration.detect import _Detector, detect_cameras
    from freipose.geometry import CameraRig
    from freipose.io.video import FrameSource
    from freipose.synth.board import default_board, write_board_videos
    from freipose.synth.rig import default_rig

    full = default_rig(4, size=(640, 480))
    rig = CameraRig((full[1],), full.metadata)
    board = default_board()
    videos, _ = write_board_videos(tmp_path, rig, board, 40, seed=4, fmt=".mp4", progress=False)
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
    a, b = np.isfinite(ref[..., 0]), np.isfinite(tracked[..., 0])
    assert a.sum() > 200
    assert (a & ~b).sum() <= 0.01 * a.sum() and not (b & ~a).any()
    both = a & b
    diff = np.abs(ref[both] - tracked[both]).max(axis=-1)
    assert np.mean(diff < 1e-3) > 0.99 and diff.max() < 0.1
    # detect_cameras tracks through videos (one process, same chunks)
    (dets,) = detect_cameras([video], board, jobs=1, progress=False)
    np.testing.assert_array_equal(np.isfinite(dets.points[..., 0]), b)
    np.testing.assert_allclose(dets.points[b], tracked[b])
