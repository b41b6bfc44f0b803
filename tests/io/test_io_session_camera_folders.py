"""Sessions with each camera's video in a folder of its own (sleap-anipose's layout,
``session/<camera>/<any name>.mp4``) are read like ``session/<camera>.mp4`` by every command
that reads a session: predict, detect, labels select, label and render."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.io.poses import read_poses_h5
from freipose.io.session import discover_sessions
from freipose.io.video import MediaError, find_camera_videos

sys.path.insert(0, str(Path(__file__).parents[1] / "predict"))
from predict_helpers import TOY_KEYPOINTS, toy_rig, toy_session, toy_training_samples  # noqa: E402

T = 8


def _touch(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"")
    return path


def test_find_camera_videos_both_layouts(tmp_path):
    flat = {c: _touch(tmp_path / "flat" / f"{c}.mp4") for c in ("cam0", "cam1")}
    assert find_camera_videos(tmp_path / "flat") == flat
    nested = {c: _touch(tmp_path / "nested" / c / f"{c}-2024.mp4") for c in ("back", "side")}
    _touch(tmp_path / "nested" / "back" / "back.slp")  # labels beside the video
    _touch(tmp_path / "nested" / "calibration" / "board.toml")  # a folder without a video
    _touch(tmp_path / "nested" / ".hidden" / "x.mp4")
    assert find_camera_videos(tmp_path / "nested") == nested
    mixed = tmp_path / "mixed"
    both = {"a": _touch(mixed / "a.mkv"), "b": _touch(mixed / "b" / "rec.mp4")}
    _touch(mixed / "calibration" / "a.mp4")  # board videos beside the session's own videos
    _touch(mixed / "calibration" / "b.mp4")
    assert find_camera_videos(mixed) == both


def test_find_camera_videos_refuses_ambiguous_folders(tmp_path):
    _touch(tmp_path / "s" / "cam0" / "one.mp4")
    _touch(tmp_path / "s" / "cam0" / "two.mp4")
    with pytest.raises(
        MediaError, match=r"2 videos \(one.mp4, two.mp4\) in the folder of camera 'cam0'"
    ):
        find_camera_videos(tmp_path / "s")
    _touch(tmp_path / "t" / "cam0.mp4")
    _touch(tmp_path / "t" / "cam0" / "one.mp4")
    with pytest.raises(MediaError, match="camera 'cam0' has two videos"):
        find_camera_videos(tmp_path / "t")
    (tmp_path / "u" / "cam0").mkdir(parents=True)
    with pytest.raises(MediaError, match=r"no videos found .* <camera>/<video>"):
        find_camera_videos(tmp_path / "u")


@pytest.fixture(scope="module")
def nested(tmp_path_factory):
    """(session in the camera-folder layout, tiny model.pt)."""
    from freipose.nn.config import config_from_dict
    from freipose.nn.train import train_pose
    from freipose.skeleton import Skeleton

    root = tmp_path_factory.mktemp("nested")
    rig = toy_rig()
    toy_session(root / "rec", rig, T)
    for cam in rig.names:  # rearranged: rec/<camera>/<camera>_top.mkv
        (root / "rec" / cam).mkdir()
        (root / "rec" / f"{cam}.mkv").rename(root / "rec" / cam / f"{cam}_top.mkv")
    cfg = config_from_dict(
        {"model": {"preset": "tiny", "cube_size": 300.0, "init": "scratch"},
         "schedule": {"steps": 1, "checkpoint_every": 1, "eval_every": 1},
         "augment": {"enabled": False}}
    )  # fmt: skip
    torch.manual_seed(0)
    model = train_pose(
        cfg, root / "run", toy_training_samples(2, rig), Skeleton("toy", TOY_KEYPOINTS),
        progress=False,
    )  # fmt: skip
    return root / "rec", model


def _ok(args):
    res = CliRunner().invoke(cli, [str(a) for a in args])
    assert res.exit_code == 0, res.output
    assert "no videos found" not in res.output
    return res


def test_every_command_reads_the_camera_folder_layout(nested, tmp_path):
    session, model = nested
    (s,) = discover_sessions([session])
    assert s.cameras == ["cam0", "cam1", "cam2"] and s.num_frames == T
    assert s.videos["cam1"] == session / "cam1" / "cam1_top.mkv"
    _ok(["detect", session, "--method", "bgsub", "-o", tmp_path / "boxes.h5"])
    assert (tmp_path / "boxes.h5").stat().st_size > 0
    _ok(["predict", session, "--model", model, "--method", "bgsub", "-o", tmp_path / "p"])
    poses = tmp_path / "p" / "rec.poses.h5"
    assert read_poses_h5(poses).poses.shape == (T, 5, 3)
    _ok(["labels", "select", session, "--poses-dir", tmp_path / "p", "--n", "2",
         "--min-gap", "1", "-o", tmp_path / "sel.csv"])  # fmt: skip
    assert len((tmp_path / "sel.csv").read_text().splitlines()) == 3
    _ok(["render", session, poses, "-o", tmp_path / "r.mkv", "--frames", "0:4",
         "--tile-width", "64"])  # fmt: skip
    assert (tmp_path / "r.mkv").stat().st_size > 0


def test_label_opens_the_camera_folder_layout(nested, tmp_path):
    from freipose.labelui.startup import open_store

    session, _ = nested
    calibration = session / "calibration.toml"
    store = open_store([session], calibration, "rat", tmp_path / "l.h5", per_session=2)
    assert store.sessions["rec"].videos["cam2"] == session / "cam2" / "cam2_top.mkv"
