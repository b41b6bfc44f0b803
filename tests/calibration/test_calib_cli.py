"""``freipose calib`` / ``freipose calib board`` and their errors on bad inputs."""

from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from freipose.calibration.board_files import load_board
from freipose.calibration.boards import CharucoBoard
from freipose.cli.main import cli


def _run(args):
    r = CliRunner().invoke(cli, args, catch_exceptions=False)
    return r.exit_code, r.output


def test_board_image(tmp_path, shared_data):
    code, out = _run(
        ["calib", "board", "examples/board.toml", "-o", str(tmp_path / "b.png"), "--dpi", "50.8"]
    )
    assert code == 0, out
    img = cv2.imread(str(tmp_path / "b.png"), cv2.IMREAD_GRAYSCALE)
    board = load_board("examples/board.toml")
    assert img.shape == (round(board.size_mm[1] * 2), round(board.size_mm[0] * 2))
    # the printed board is detected
    ids, _ = __import__("freipose.calibration.detect", fromlist=["x"]).detect_image(
        np.pad(img, 20, constant_values=255), board
    )
    assert len(ids) == len(board.object_points)


def test_board_missing_field(tmp_path):
    p = tmp_path / "b.toml"
    p.write_text(
        'type = "charuco"\nsquares_x = 5\nsquares_y = 7\nsquare_size = 40\n'
        'dictionary = "DICT_6X6_250"\n'
    )
    code, out = _run(["calib", "board", str(p), "-o", str(tmp_path / "b.png")])
    assert code != 0 and "marker_size" in out and "Traceback" not in out


def _charuco_folder(tmp_path, shared_data, name="cam0", copies=1):
    d = tmp_path / name
    d.mkdir()
    for i in range(copies):
        shutil.copy(shared_data / "opencv-charuco-tutorial" / "choriginal.jpg", d / f"{i:03d}.jpg")
    return d


def test_wrong_dictionary(tmp_path, shared_data):
    d = _charuco_folder(tmp_path, shared_data)
    code, out = _run(
        [
            "calib",
            str(d),
            "--board-type",
            "charuco",
            "--squares-x",
            "5",
            "--squares-y",
            "7",
            "--square-size",
            "40",
            "--marker-size",
            "20",
            "--dictionary",
            "DICT_4X4_50",
            "-o",
            str(tmp_path / "c.toml"),
            "-j",
            "1",
        ]
    )
    assert code != 0
    assert "never detected" in out and "DICT_6X6" in out, out


def test_camera_never_sees_board(tmp_path, shared_data):
    good = _charuco_folder(tmp_path, shared_data, "cam0")
    blank = tmp_path / "cam1"
    blank.mkdir()
    cv2.imwrite(str(blank / "000.png"), np.full((480, 640, 3), 128, np.uint8))
    board = CharucoBoard(5, 7, 40.0, 20.0, "DICT_6X6_250")
    (tmp_path / "b.toml").write_text(
        "\n".join(f"{k} = {v!r}".replace("'", '"') for k, v in board.to_dict().items()).replace(
            "False", "false"
        )
    )
    code, out = _run(
        [
            "calib",
            str(good),
            str(blank),
            "--board",
            str(tmp_path / "b.toml"),
            "-o",
            str(tmp_path / "c.toml"),
            "-j",
            "1",
        ]
    )
    assert code != 0 and "camera cam1" in out and "never detected" in out, out
    assert not (tmp_path / "c.toml").exists()


def test_unreadable_video_and_empty_folder(tmp_path):
    bad = tmp_path / "cam0.mp4"
    bad.write_text("not a video")
    code, out = _run(
        ["calib", str(bad), "--board", "examples/board.toml", "-o", str(tmp_path / "c.toml")]
    )
    assert code != 0 and "cam0.mp4" in out and "Traceback" not in out, out
    empty = tmp_path / "cam1"
    empty.mkdir()
    code, out = _run(
        ["calib", str(empty), "--board", "examples/board.toml", "-o", str(tmp_path / "c.toml")]
    )
    assert code != 0 and "no images" in out, out
    code, out = _run(["calib", "--board", "examples/board.toml", "-o", str(tmp_path / "c.toml")])
    assert code != 0 and "no INPUT" in out


@pytest.mark.parametrize("name", ["board.toml", "board.json"])
def test_board_files_roundtrip(tmp_path, name):
    from freipose.calibration.board_files import save_board

    b = load_board("examples/board.toml")
    save_board(b, tmp_path / name)
    assert load_board(tmp_path / name) == b


def test_stereo_cli_with_report(tmp_path, shared_data):
    import json

    from freipose.io.calibration import load_calibration

    src = shared_data / "opencv-bouguet-stereo" / "images"
    dirs = []
    for side in ("left", "right"):
        d = tmp_path / side
        d.mkdir()
        for f in sorted(src.glob(f"{side}0[1-8].jpg")):
            (d / f.name).symlink_to(f)
        dirs.append(str(d))
    out = tmp_path / "stereo.toml"
    code, text = _run(
        [
            "calib",
            *dirs,
            "--board-type",
            "chessboard",
            "--inner-corners-x",
            "9",
            "--inner-corners-y",
            "6",
            "--square-size",
            "30",
            "-o",
            str(out),
            "--report",
            str(tmp_path / "rep"),
            "-j",
            "1",
            "--aspect",
            "square",
            "--no-refine-board",
            "--no-view-weights",
        ]
    )
    assert code == 0, text
    rig = load_calibration(out)
    assert rig.names == ["left", "right"] and "camera left" in rig.metadata["world"]
    # the solver options reach the pipeline
    assert all(c.K[0, 0] == c.K[1, 1] for c in rig)
    assert rig.metadata["intrinsics_model"]["left"]["focal"] == "fx = fy"
    assert "board_point_corrections_rms_mm" not in rig.metadata
    assert rig.metadata["view_weights"] is False
    assert abs(np.linalg.norm(rig["right"].center) - 99.8) < 1.5
    summary = json.loads((tmp_path / "rep" / "summary.json").read_text())
    assert summary["cameras"]["left"]["frames_with_detections"] == 8
    assert summary["cameras"]["right"]["reprojection_rms_px"] < 0.5
    assert summary["camera_graph"]["shared_frames"] == {"left-right": 8}
    for name in ("errors_left.png", "coverage_right.png", "rig_3d.png"):
        assert (tmp_path / "rep" / name).stat().st_size > 1000
    # intrinsics only, reusing the cached detections
    code, text = _run(
        [
            "calib",
            *dirs,
            "--board-type",
            "chessboard",
            "--inner-corners-x",
            "9",
            "--inner-corners-y",
            "6",
            "--square-size",
            "30",
            "-o",
            str(out),
            "--intrinsics-only",
        ]
    )
    assert code == 0, text
    assert "intrinsics only" in load_calibration(out).metadata["world"]


def test_cli_stores_the_up_direction(tmp_path, shared_data):
    from freipose.io.calibration import load_calibration
    from freipose.io.calibration_world import world_up

    src = shared_data / "opencv-bouguet-stereo" / "images"
    dirs = []
    for side in ("left", "right"):
        d = tmp_path / side
        d.mkdir()
        for f in sorted(src.glob(f"{side}0[1-6].jpg")):
            (d / f.name).symlink_to(f)
        dirs.append(str(d))
    out = tmp_path / "stereo.toml"
    base = ["calib", *dirs, "--board-type", "chessboard", "--inner-corners-x", "9",
            "--inner-corners-y", "6", "--square-size", "30", "-o", str(out), "-j", "1",
            "--no-refine-board"]  # fmt: skip
    code, text = _run(base)
    assert code == 0, text
    assert "up direction is unknown" in text and world_up(load_calibration(out)) is None
    # one line per camera by default; the solver's rounds and tests are debug messages (-v)
    assert "bundle adjustment: RMS" in text and "bundle round" not in text and "chi2" not in text
    code, verbose = _run(["-v", *base])
    assert code == 0 and "bundle round" in verbose and "chi2" in verbose, verbose
    lines = [ln for ln in text.splitlines() if ln.startswith(("left:", "right:"))]
    assert len(lines) == 2 and all("reprojection RMS" in ln and " ± " in ln for ln in lines)
    code, text = _run([*base, "--up", "0,-2,0"])
    assert code == 0 and "up direction is unknown" not in text, text
    up = world_up(load_calibration(out))
    assert up.up.tolist() == [0, -1, 0] and up.source == "given with --up" and up.floor is None
    code, text = _run([*base, "--origin-frame", "0"])
    assert code == 0, text
    up = world_up(load_calibration(out))
    assert up.up.tolist() == [0, 0, 1] and up.floor == 0.0 and "frame 0" in up.source
    code, text = _run([*base, "--origin-frame", "0", "--up", "0,0,1"])
    assert code != 0 and "pass one" in text
