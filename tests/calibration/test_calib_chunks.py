"""Detection work planning: every frame decoded once, in few contiguous chunks."""

from __future__ import annotations

import numpy as np
import pytest

from freipose.calibration.detect import plan_chunks


@pytest.mark.parametrize(
    "frames, jobs", [([150] * 4, 2), ([150] * 4, 8), ([100, 0, 37], 3), ([5], 16), ([1000], 1)]
)
def test_plan_chunks_covers_every_frame_once(frames, jobs):
    chunks = plan_chunks(frames, jobs)
    for ci, n in enumerate(frames):
        own = sorted((a, b) for c, a, b in chunks if c == ci)
        covered = np.zeros(n, int)
        for a, b in own:
            assert 0 <= a < b <= n
            covered[a:b] += 1
        assert (covered == 1).all()
    # no more chunks than needed: one per camera when there are at least as many cameras as
    # processes; otherwise about one per process
    if len([n for n in frames if n]) >= jobs:
        assert len(chunks) == len([n for n in frames if n])
    else:
        assert len(chunks) <= jobs + len(frames)


def test_plan_chunks_balances_processes():
    chunks = plan_chunks([300], 4)
    assert len(chunks) == 4
    assert {b - a for _, a, b in chunks} == {75}
    assert plan_chunks([], 4) == [] and plan_chunks([0, 0], 2) == []


def test_detect_chunk_reports_progress(tmp_path):
    import cv2

    from freipose.calibration.boards import ChessboardBoard
    from freipose.calibration.detect import _detect_chunk

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
