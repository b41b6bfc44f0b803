"""``freipose calib``: outputs checked before the detection, ``--format``, dead workers."""

from __future__ import annotations

import multiprocessing as mp
import os

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from freipose.calibration.detect_videos import _detect_chunk
from freipose.cli.main import cli

BOARD = "examples/board.toml"


def _run(args):
    r = CliRunner().invoke(cli, ["calib", *map(str, args)], catch_exceptions=False)
    return r.exit_code, r.output


@pytest.fixture
def no_detection(monkeypatch):
    """Fail the test if the board detection starts."""

    def detect(*args, **kwargs):
        raise AssertionError("the detection ran before the outputs were checked")

    monkeypatch.setattr("freipose.calibration.pipeline.detect_cameras", detect)


def _videos(tmp_path, n=2):
    """``n`` input files (never opened: the outputs are checked first)."""
    out = []
    for i in range(n):
        p = tmp_path / f"cam{i}.mp4"
        p.write_bytes(b"not read")
        out.append(p)
    return out


def test_unknown_output_suffix_fails_before_detection(tmp_path, no_detection):
    code, out = _run([*_videos(tmp_path), "--board", BOARD, "-o", tmp_path / "out.xyz"])
    assert code != 0 and "Traceback" not in out, out
    assert out.strip() == (
        f"Error: cannot tell the calibration format of -o {tmp_path / 'out.xyz'} from its "
        f"suffix '.xyz': expected .toml (toml), .json (mjson), .yaml or .yml (jarvis); rename "
        f"it (e.g. -o {tmp_path / 'out.toml'}) or pass --format, one of anipose, jarvis, "
        f"mjson, toml"
    )
    assert not (tmp_path / "out.detections").exists()


def _bad_outputs(tmp_path):
    """``(extra args, expected message part)`` for outputs that cannot be written."""
    (tmp_path / "a_file").write_text("x")
    jarvis = tmp_path / "jarvis"
    jarvis.mkdir()
    (jarvis / "other.yaml").write_text("%YAML:1.0\n")
    return [
        (["-o", tmp_path / "c.mat"], "'.mat' is the dannce format, which FreiPose reads but"),
        (["-o", tmp_path / "c.toml", "--format", "dannce"], "--format dannce: not a calib"),
        (["-o", tmp_path / "c.yaml"], "a JARVIS .yaml file holds one camera, the rig has 2"),
        (["-o", tmp_path / "cam0.mp4", "--format", "toml"], "exists and is not a calibration"),
        (["-o", BOARD], "exists and is not a calibration file"),
        (["-o", tmp_path / "a_file" / "c.toml"], "is a file, not a folder"),
        (["-o", tmp_path / "c.toml", "--report", tmp_path / "a_file" / "r"], "--report"),
        (["-o", tmp_path], "is a folder; expected a calibration file name"),
        (["-o", jarvis, "--format", "jarvis"], "already holds camera files ['other.yaml']"),
        (["-o", tmp_path / "a_file", "--format", "jarvis"], "a JARVIS calibration is a folder"),
    ]


def test_bad_outputs_fail_before_detection(tmp_path, no_detection):
    inputs = _videos(tmp_path)
    before = sorted(tmp_path.rglob("*"))
    for args, part in _bad_outputs(tmp_path):
        code, out = _run([*inputs, "--board", BOARD, *args])
        assert code != 0 and part in out and "Traceback" not in out, (args, out)
        assert len(out.strip().splitlines()) == 1, out
    assert not list(tmp_path.rglob("*.detections")), before


def test_format_option_writes_the_chosen_format(tmp_path, shared_data):
    from freipose.io.calibration import load_calibration

    src = shared_data / "opencv-bouguet-stereo" / "images"
    dirs = []
    for side in ("left", "right"):
        d = tmp_path / side
        d.mkdir()
        for f in sorted(src.glob(f"{side}0[1-6].jpg")):
            (d / f.name).symlink_to(f)
        dirs.append(d)
    board = ["--board-type", "chessboard", "--inner-corners-x", "9", "--inner-corners-y", "6"]
    fast = ["--square-size", "30", "-j", "1", "--no-refine-board", "--no-view-weights"]

    def calib(*args):
        code, text = _run([*dirs, *board, *fast, *args])
        assert code == 0, text

    calib("-o", tmp_path / "st.toml")
    rig = load_calibration(tmp_path / "st.toml")
    # --format toml under another suffix: the same file (the same cached detections)
    calib("-o", tmp_path / "st.cal", "--format", "toml")
    assert (tmp_path / "st.cal").read_bytes() == (tmp_path / "st.toml").read_bytes()
    # an existing calibration is replaced
    calib("-o", tmp_path / "st.cal", "--format", "toml")
    calib("-o", tmp_path / "st.txt", "--format", "mjson")
    m = load_calibration(tmp_path / "st.txt", "mjson")
    assert m.names == rig.names
    np.testing.assert_allclose(m.centers, rig.centers, atol=1e-6)
    calib("-o", tmp_path / "st_jarvis", "--format", "jarvis")
    assert sorted(p.name for p in (tmp_path / "st_jarvis").iterdir()) == [
        "left.yaml",
        "right.yaml",
    ]
    j = load_calibration(tmp_path / "st_jarvis")
    np.testing.assert_allclose(j.centers, rig.centers, atol=1e-6)


def _die_in_worker(*args):
    """``_detect_chunk`` that ends a worker process without an error (runs in this one)."""
    if mp.parent_process() is not None:
        os._exit(1)
    return _detect_chunk(*args)


def test_dead_worker_is_one_line(tmp_path, monkeypatch):
    # the workers unpickle the chunk function by name: this module's _die_in_worker
    monkeypatch.setattr("freipose.calibration.detect_videos._detect_chunk", _die_in_worker)
    inputs = []
    for i in range(4):
        d = tmp_path / f"cam{i}"
        d.mkdir()
        cv2.imwrite(str(d / "000.png"), np.full((48, 64, 3), 128, np.uint8))
        inputs.append(d)
    code, out = _run([*inputs, "--board", BOARD, "-o", tmp_path / "c.toml", "-j", "2"])
    assert code != 0 and "Traceback" not in out, out
    # (a piped progress bar prints its last line when it closes; the error is one line)
    lines = [ln for ln in out.strip().splitlines() if not ln.startswith("detecting board:")]
    assert lines == [
        "Error: a worker process died: it exited with status 1 (its own error, if any, is "
        "printed above); run again with one job (--jobs 1) to see the error in this process"
    ]


def test_broken_link_in_image_folder(tmp_path):
    d = tmp_path / "cam0"
    d.mkdir()
    cv2.imwrite(str(d / "000.png"), np.full((48, 64, 3), 128, np.uint8))
    (d / "001.png").symlink_to(tmp_path / "gone.png")
    code, out = _run([d, "--board", BOARD, "-o", tmp_path / "c.toml", "-j", "1"])
    assert code != 0 and "Traceback" not in out, out
    assert out.strip() == (
        f"Error: {d / '001.png'}: a broken link (or a file removed meanwhile) in the image "
        f"folder {d}; remove it or make it point to the image"
    )
