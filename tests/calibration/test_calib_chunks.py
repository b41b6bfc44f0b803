"""Detection work planning: every frame decoded once, in contiguous chunks of a fixed size."""

from __future__ import annotations

import numpy as np
import pytest

from freipose.calibration.detect_videos import plan_chunks


@pytest.mark.parametrize(
    "frames, size",
    [([150] * 4, 100), ([150] * 4, 8), ([100, 0, 37], 30), ([5], 16), ([1000], 1000)],
)
def test_plan_chunks_covers_every_frame_once(frames, size):
    chunks = plan_chunks(frames, size)
    for ci, n in enumerate(frames):
        own = sorted((a, b) for c, a, b in chunks if c == ci)
        covered = np.zeros(n, int)
        for a, b in own:
            assert 0 <= a < b <= n
            covered[a:b] += 1
        assert (covered == 1).all()
        lengths = [b - a for a, b in own]
        if n:  # as few chunks as the size allows, of equal length within a camera
            assert max(lengths) <= size and len(own) == -(-n // size)
            assert max(lengths) - min(lengths) <= 1
    lengths = [b - a for _, a, b in chunks]
    assert lengths == sorted(lengths, reverse=True)  # longest first


def test_plan_chunks_edge_cases():
    assert plan_chunks([300], 75) == [(0, 0, 75), (0, 75, 150), (0, 150, 225), (0, 225, 300)]
    assert plan_chunks([], 4) == [] and plan_chunks([0, 0], 2) == []


def test_parallel_detection_equals_serial_detection(tmp_path):
    """The chunks do not depend on the process count, so neither do the detections (the
    progress bar's queue is in use: progress on)."""
    from freipose.calibration.detect_videos import detect_cameras
    from freipose.geometry import CameraRig
    from freipose.synth.board import default_board, write_board_videos
    from freipose.synth.rig import default_rig

    full = default_rig(4, size=(320, 240))
    rig = CameraRig(tuple(full)[:2], full.metadata)
    board = default_board()
    videos, _ = write_board_videos(tmp_path, rig, board, 45, seed=5, fmt=".mp4", progress=False)
    paths = [videos[c.name] for c in rig]
    one = detect_cameras(paths, board, jobs=1, progress=False)
    two = detect_cameras(paths, board, jobs=2, progress=True)
    assert sum(int(d.mask.sum()) for d in one) > 100
    for a, b in zip(one, two):
        np.testing.assert_array_equal(a.points, b.points)


def test_detect_chunk_reports_progress(tmp_path):
    import cv2

    from freipose.calibration.boards import ChessboardBoard
    from freipose.calibration.detect_videos import _detect_chunk

    board = ChessboardBoard(4, 3, 20.0)
    img = cv2.resize(board.texture(2.0), None, fx=1.0, fy=1.0)
    frame = np.full((img.shape[0] + 40, img.shape[1] + 40), 255, np.uint8)
    frame[20:-20, 20:-20] = img
    for i in range(23):
        cv2.imwrite(str(tmp_path / f"f{i:02d}.png"), frame)

    class Sink:
        total = 0

        def put(self, n):
            Sink.total += n

    start, pts = _detect_chunk(str(tmp_path), board, 2, 23, Sink())
    assert start == 2 and pts.shape == (21, 12, 2)
    assert Sink.total == 21
    assert np.isfinite(pts).all()
