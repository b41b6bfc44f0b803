"""H.264 MP4 writing: frames survive the encoder, odd sizes are padded, Chromium plays it."""

from __future__ import annotations

import numpy as np
import pytest
from browser import video_page, video_state

from freipose.io.video import FrameSource, MediaError, VideoWriter


def _frames(n: int, w: int, h: int) -> list[np.ndarray]:
    out = []
    for i in range(n):
        img = np.full((h, w, 3), 30, np.uint8)
        img[h // 4 : h // 2, 4 * i : 4 * i + 16] = (40, 200, 250)  # a moving orange block
        out.append(img)
    return out


def test_h264_round_trip_and_odd_size(tmp_path):
    p = tmp_path / "clip.mp4"
    frames = _frames(12, 81, 61)
    with VideoWriter(p, 25.0, (81, 61), codec="h264") as w:
        for f in frames:
            w.write(f)
        assert not p.exists()  # only the partial file while writing
    assert w.frames == 12 and p.is_file()
    assert p.read_bytes()[4:8] == b"ftyp"
    head = p.read_bytes()[:4096]
    assert b"moov" in head and b"avcC" in head  # +faststart: the H.264 index before the frames
    src = FrameSource(p)
    assert src.size == (82, 62) and src.num_frames == 12 and src.fps == pytest.approx(25.0)
    for i in (0, 7, 11):
        got = src[i][:61, :81].astype(int)
        assert np.abs(got - frames[i]).mean() < 3.0
        assert np.abs(got[20, 4 * i + 8] - (40, 200, 250)).max() < 25
    assert list(tmp_path.iterdir()) == [p]


def test_h264_errors_and_abort(tmp_path):
    with pytest.raises(MediaError, match=r"\.mp4"):
        VideoWriter(tmp_path / "x.avi", 10, (32, 24), codec="h264")
    with pytest.raises(MediaError, match="unknown codec"):
        VideoWriter(tmp_path / "x.mp4", 10, (32, 24), codec="vp9")
    with pytest.raises(RuntimeError), VideoWriter(tmp_path / "z.mp4", 10, (32, 24), "h264") as w:
        w.write(np.zeros((24, 32, 3), np.uint8))
        raise RuntimeError("stop")
    assert list(tmp_path.iterdir()) == []


def test_h264_video_plays_in_chromium(tmp_path, chromium):
    p = tmp_path / "clip.mp4"
    with VideoWriter(p, 25.0, (96, 64), codec="h264") as w:
        for f in _frames(20, 96, 64):
            w.write(f)
    chromium.get(video_page(p).as_uri())
    state = video_state(chromium)
    assert state["error"] is None and state["readyState"] >= 2, state
    assert (state["videoWidth"], state["videoHeight"]) == (96, 64)


def test_h264_without_an_encoder_says_what_to_do(tmp_path, monkeypatch):
    import imageio_ffmpeg

    monkeypatch.setattr(imageio_ffmpeg, "get_ffmpeg_exe", lambda: str(tmp_path / "no-ffmpeg"))
    with pytest.raises(MediaError, match="cannot start the H.264 encoder"):
        VideoWriter(tmp_path / "a.mp4", 10, (32, 24), codec="h264")

    def missing() -> str:
        raise RuntimeError("No ffmpeg exe could be found")

    monkeypatch.setattr(imageio_ffmpeg, "get_ffmpeg_exe", missing)
    with pytest.raises(MediaError, match="pip install imageio-ffmpeg"):
        VideoWriter(tmp_path / "b.mp4", 10, (32, 24), codec="h264")
    assert list(tmp_path.iterdir()) == []


def test_h264_encoder_failure_leaves_no_file(tmp_path):
    w = VideoWriter(tmp_path / "c.mp4", 0.0, (32, 24), codec="h264")  # ffmpeg refuses 0 fps
    with pytest.raises(MediaError, match="H.264 encoder"):
        for _ in range(50):
            w.write(np.zeros((24, 32, 3), np.uint8))
        w.close()
    assert list(tmp_path.iterdir()) == []
