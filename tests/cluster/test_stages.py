"""detect, smooth, analyze variables and render through the local executor: their outputs
equal a direct run's bit for bit, a rerun submits nothing, ``freipose jobs`` shows the units
of any stage, and a unit that fails is reported and finished by ``--resume``."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from predict_helpers import BlobEstimator, h5_equal, make_session

from freipose.cli.main import cli
from freipose.io.lock import output_lock
from freipose.io.poses import PoseData, write_poses_h5
from freipose.io.session import discover_sessions
from freipose.predict.run import predict_session
from freipose.skeleton import load_skeleton

T = 24
UNITS = ["--executor", "local", "--parallel", "2"]


def _run(*args: object) -> str:
    res = CliRunner().invoke(cli, [str(a) for a in args])
    assert res.exit_code == 0, res.output
    return res.output


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict:
    """Two 24-frame sessions with their poses (blob estimator) and a rat's poses file."""
    root = tmp_path_factory.mktemp("stages")
    poses = []
    for name in ("s0", "s1"):
        make_session(root / name, T)
        (s,) = discover_sessions([root / name])
        poses.append(predict_session(s, BlobEstimator(), root / "poses", batch_size=4,
                                     chunk_frames=8, progress=False).path)  # fmt: skip
    rat = load_skeleton("rat")
    rng = np.random.default_rng(0)
    walk = np.cumsum(rng.normal(0, 2, (60, 1, 3)), 0) + rng.normal(0, 30, (1, 12, 3))
    conf = np.ones((60, 12), np.float32)
    rat_poses = root / "rat.poses.h5"
    write_poses_h5(PoseData(walk.astype(np.float32), conf, rat.keypoints, np.arange(60), 30.0,
                            skeleton=rat), rat_poses)  # fmt: skip
    with h5py.File(rat_poses, "a") as f:
        f.attrs["complete"] = True
    return {"root": root, "sessions": [root / "s0", root / "s1"], "poses": poses,
            "rat": rat_poses}  # fmt: skip


DETECT = ["--method", "bgsub", "--batch-size", "4", "--bg-samples", "10"]


def test_detect_units_equal_a_direct_run(inputs, tmp_path):
    s0 = inputs["sessions"][0]
    _run("detect", s0, *DETECT, "-o", tmp_path / "direct.h5")
    out = tmp_path / "boxes" / "s0.boxes.h5"
    said = _run("detect", s0, *DETECT, "-o", out, *UNITS, "--chunk-frames", "8")
    assert "3 units done (3 jobs submitted in this run)" in said
    assert h5_equal(tmp_path / "direct.h5", out) == []
    assert not (out.parent / ".jobs" / out.name / "parts").exists()
    again = _run("detect", s0, *DETECT, "-o", out, *UNITS, "--chunk-frames", "8")
    assert "(0 jobs submitted in this run)" in again
    status = _run("jobs", out)
    assert "units of `freipose detect`" in status and "s0: 3 done" in status
    assert "s0: 3 done" in _run("jobs", out.parent)  # the folder lists its files' jobs


def test_detect_units_with_a_detector_equal_a_direct_run(inputs, tmp_path):
    import torch

    from freipose.detect.detector import save_checkpoint
    from freipose.detect.model import DetectorConfig, DetectorNet

    torch.manual_seed(0)
    det = tmp_path / "det.pt"
    save_checkpoint(det, DetectorNet(DetectorConfig(input_size=64, width=0.25, neck_channels=8)))
    args = [inputs["sessions"][1], "--model", det, "--device", "cpu", "--batch-size", "4",
            "--threads", "1"]  # fmt: skip
    _run("detect", *args, "-o", tmp_path / "direct.h5")
    out = tmp_path / "units.h5"
    said = _run("detect", *args, "-o", out, *UNITS, "--chunk-frames", "12")
    assert "2 units done (2 jobs submitted in this run)" in said
    assert h5_equal(tmp_path / "direct.h5", out) == []


def test_detect_unit_that_fails_is_reported_and_resumed(inputs, tmp_path):
    s0 = inputs["sessions"][0]
    _run("detect", s0, *DETECT, "-o", tmp_path / "direct.h5")
    out = tmp_path / "s0.boxes.h5"
    part = tmp_path / ".jobs" / out.name / "parts" / "1-of-3.boxes.h5"
    part.parent.mkdir(parents=True)
    with output_lock(part, "boxes part"):  # this live process holds it: the unit fails
        res = CliRunner().invoke(cli, ["detect", str(s0), *DETECT, "-o", str(out), *UNITS,
                                       "--chunk-frames", "8", "--max-retries", "1"])  # fmt: skip
        assert res.exit_code != 0
        assert "1 of 3 units failed" in res.output and "s0.1-of-3: OutputLockedError" in res.output
        assert f"freipose jobs {out} --resume" in res.output
        assert not out.exists()
        assert "s0: 2 done, 1 failed" in _run("jobs", out)
    resumed = _run("jobs", out, "--resume")
    assert "s0: 3 done" in resumed
    assert h5_equal(tmp_path / "direct.h5", out) == []


def test_smooth_units_equal_a_direct_run(inputs, tmp_path):
    poses = inputs["poses"]
    _run("smooth", *poses, "-o", tmp_path / "direct")
    said = _run("smooth", *poses, "-o", tmp_path / "units", *UNITS)
    assert "2 units done (2 jobs submitted in this run)" in said
    for p in poses:
        assert h5_equal(tmp_path / "direct" / p.name, tmp_path / "units" / p.name) == []
    status = _run("jobs", tmp_path / "units")
    assert "units of `freipose smooth`" in status and "s0: 1 done" in status
    plan = tmp_path / "poses" / ".jobs" / "plan.json"  # a prediction's job in that folder
    plan.parent.mkdir(parents=True)
    plan.write_text('{"command": "predict"}')
    res = CliRunner().invoke(cli, ["smooth", *map(str, poses), "-o", str(plan.parents[1]), *UNITS])
    assert res.exit_code != 0 and "holds the job of `freipose predict`" in res.output, res.output
    assert plan.read_text() == '{"command": "predict"}'


def test_variables_unit_equals_a_direct_run(inputs, tmp_path):
    _run("analyze", "variables", inputs["rat"], "-o", tmp_path / "direct.vars.h5")
    out = tmp_path / "units" / "rat.vars.h5"
    said = _run("analyze", "variables", inputs["rat"], "-o", out, *UNITS)
    assert "1 units done (1 jobs submitted in this run)" in said
    assert h5_equal(tmp_path / "direct.vars.h5", out) == []


def test_render_unit_equals_a_direct_run(inputs, tmp_path):
    s0, p0 = inputs["sessions"][0], inputs["poses"][0]
    args = ["--frames", "0:8", "--tile-width", "64"]
    _run("render", s0, p0, "-o", tmp_path / "direct.mkv", *args)
    out = tmp_path / "units" / "s0.mkv"
    said = _run("render", s0, p0, "-o", out, *args, *UNITS)
    assert "1 units done (1 jobs submitted in this run)" in said
    # the same encoded stream: the same size and every decoded frame equal (two direct runs
    # differ in the container's random segment id and date, and in nothing else)
    assert (tmp_path / "direct.mkv").stat().st_size == out.stat().st_size
    direct, units = _decoded(tmp_path / "direct.mkv"), _decoded(out)
    assert len(direct) == 8 and all(
        np.array_equal(a, b) for a, b in zip(direct, units, strict=True)
    )


def _decoded(path: Path) -> list[np.ndarray]:
    import cv2

    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        frames.append(img)
    cap.release()
    return frames
