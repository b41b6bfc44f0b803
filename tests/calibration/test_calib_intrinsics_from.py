"""Intrinsics from a separate recording (``--intrinsics-from``): a calibration file."""

from __future__ import annotations

import numpy as np
import pytest
from calib_helpers import board_detections, rig_errors

from freipose.calibration.boards import CharucoBoard
from freipose.calibration.intrinsics import CalibrationError
from freipose.calibration.options import CalibrationOptions
from freipose.calibration.pipeline import calibrate_detections, intrinsics_from
from freipose.io.calibration import load_calibration, save_calibration
from freipose.testing import make_circle_rig

BOARD = CharucoBoard(8, 6, 40.0, 30.0, "DICT_4X4_50")


def test_intrinsics_from_file(tmp_path):
    rig = make_circle_rig(4, radius=700.0, height=400.0, distortion=True)
    dets = board_detections(rig, BOARD.object_points, BOARD.size_mm, 60, noise_px=0.2)[0]
    path = tmp_path / "intrinsics.toml"
    save_calibration(rig, path)
    fixed = intrinsics_from(path, [d.name for d in dets], BOARD)
    res = calibrate_detections(
        dets, BOARD, CalibrationOptions(fixed_intrinsics=fixed, progress=False)
    )
    for est, truth in zip(res.rig, rig):
        assert (est.K == truth.K).all() and (est.dist == truth.dist).all()
    dc, rot, _ = rig_errors(res.rig, rig)
    assert dc.max() < 2.0 and rot.max() < 0.2
    assert res.standard_errors == {d.name: {} for d in dets}
    with pytest.raises(CalibrationError, match="--intrinsics-from .*camera.* camX are not in"):
        intrinsics_from(path, ["cam0", "camX"], BOARD)


def test_intrinsics_from_folder_of_recordings(tmp_path):
    import cv2
    from calib_helpers import rendered_view

    truth = {}
    for i in (0, 1):
        rig, board, _poses, images = rendered_view(i, 60, 11 + i, slice(4, None, 2))
        cam = rig[0]
        truth[cam.name] = cam
        (tmp_path / cam.name).mkdir()
        for k, img in enumerate(images):
            cv2.imwrite(str(tmp_path / cam.name / f"{k:03d}.png"), img)
    names = list(truth)
    fixed = intrinsics_from(tmp_path, names, board, CalibrationOptions(progress=False, jobs=1))
    assert fixed.names == names
    for name in names:
        est, t = fixed[name], truth[name]
        # (one camera's intrinsics from 28 rendered frames: a few tenths of a % to 1.5 %)
        assert abs(est.K[0, 0] / t.K[0, 0] - 1) < 0.03
        assert np.abs(est.K[:2, 2] - t.K[:2, 2]).max() < 10.0
    with pytest.raises(CalibrationError, match="no video or image folder for camera camX"):
        intrinsics_from(tmp_path, [*names, "camX"], board)


def test_cli_intrinsics_from_file(tmp_path, monkeypatch):
    from click.testing import CliRunner

    from freipose.calibration import pipeline
    from freipose.cli.main import cli

    rig = make_circle_rig(3, radius=700.0, height=400.0, distortion=True)
    dets = board_detections(rig, BOARD.object_points, BOARD.size_mm, 50, noise_px=0.2)[0]
    monkeypatch.setattr(pipeline, "detect_cameras", lambda *a, **k: dets)
    inputs = []
    for d in dets:
        (tmp_path / d.name).mkdir()
        inputs.append(str(tmp_path / d.name))
    intr = tmp_path / "intrinsics.toml"
    save_calibration(rig, intr)
    out = tmp_path / "calibration.toml"
    args = ["calib", "run", *inputs, "--board-type", "charuco", "--squares-x", "8"]
    args += ["--squares-y", "6", "--square-size", "40", "--marker-size", "30"]
    args += ["--dictionary", "DICT_4X4_50", "-o", str(out), "--intrinsics-from", str(intr)]
    r = CliRunner().invoke(cli, args, catch_exceptions=False)
    assert r.exit_code == 0, r.output
    res = load_calibration(out)
    for est, truth in zip(res, rig):
        assert np.array_equal(est.K, truth.K) and np.array_equal(est.dist, truth.dist)
    r = CliRunner().invoke(cli, [*args, "--fix-intrinsics", str(intr)], catch_exceptions=False)
    assert r.exit_code != 0 and "pass one" in r.output
