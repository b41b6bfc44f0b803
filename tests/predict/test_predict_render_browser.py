"""``freipose render -o x.mp4`` writes H.264 that plays in headless Chromium."""

from __future__ import annotations

from browser import video_page, video_state
from click.testing import CliRunner
from predict_helpers import BlobEstimator, make_session

from freipose.cli.main import cli
from freipose.io.session import discover_sessions
from freipose.predict.run import predict_session


def test_rendered_mp4_plays_in_chromium(tmp_path, chromium):
    folder = tmp_path / "rec"
    make_session(folder, 8)
    (s,) = discover_sessions([folder])
    poses = predict_session(s, BlobEstimator(), tmp_path, batch_size=4, progress=False).path
    out = tmp_path / "overlay.mp4"
    args = ["render", str(folder), str(poses), "-o", str(out), "--tile-width", "161"]
    res = CliRunner().invoke(cli, args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    chromium.get(video_page(out).as_uri())
    state = video_state(chromium)
    assert state["error"] is None and state["readyState"] >= 2, state
    assert state["videoWidth"] > 0 and state["videoWidth"] % 2 == 0
