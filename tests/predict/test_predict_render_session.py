"""``freipose render`` refuses poses of another session (name, videos, frame count) and
says that ``--force`` overrides."""

from __future__ import annotations

import pytest
from click.testing import CliRunner
from predict_helpers import BlobEstimator, make_session

from freipose.cli.main import cli
from freipose.io.session import discover_sessions
from freipose.predict.run import predict_session


@pytest.fixture(scope="module")
def days(tmp_path_factory):
    """Folders rec/day1 (12 frames) and rec/day2 (20 frames, same cameras) and day2's poses."""
    root = tmp_path_factory.mktemp("days")
    make_session(root / "rec" / "day1", 12)
    make_session(root / "rec" / "day2", 20)
    (s,) = discover_sessions([root / "rec" / "day2"])
    poses = predict_session(s, BlobEstimator(), root / "poses", batch_size=4, progress=False)
    return root, poses.path


def _render(*args):
    return CliRunner().invoke(cli, ["render", *map(str, args), "--tile-width", "64", "--no-3d"])


def test_render_refuses_another_sessions_poses(days, tmp_path):
    root, poses = days
    day1 = root / "rec" / "day1"
    out = tmp_path / "o.mkv"
    res = _render(day1, poses, "-o", out)
    assert res.exit_code != 0
    msg = " ".join(res.output.split())
    assert (
        f"{poses} does not belong to the session {day1}: the poses are of session 'day2', the "
        "videos of 'day1'; the poses cover frames up to 19, the session's videos have 12 "
        "frames. Render the poses of this session, or pass --force to draw them anyway"
    ) in msg
    assert not out.exists()


def test_force_draws_them_anyway(days, tmp_path):
    root, poses = days
    out = tmp_path / "o.mkv"
    res = _render(root / "rec" / "day1", poses, "-o", out, "--force", "--frames", "0:4")
    assert res.exit_code == 0, res.output
    assert out.is_file() and "the poses are of session 'day2'" in res.output


def test_own_session_and_renamed_videos(days, tmp_path):
    root, poses = days
    day2 = root / "rec" / "day2"
    res = _render(day2, poses, "-o", tmp_path / "o.mkv", "--frames", "0:4")
    assert res.exit_code == 0, res.output
    assert "warning" not in res.output
    other = tmp_path / "day2"  # same name, other videos
    make_session(other, 20, suffix=".avi")
    res = _render(other, poses, "-o", tmp_path / "p.mkv")
    assert res.exit_code != 0
    assert "the poses were predicted from the videos cam0: cam0.mp4" in res.output
    assert "the session has cam0: cam0.avi" in res.output and "--force" in res.output
