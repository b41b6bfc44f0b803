"""Plausibility checks after the bundle adjustment; intrinsic standard errors; --force."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import tomllib
from calib_helpers import board_detections
from click.testing import CliRunner

from freipose.calibration.boards import CharucoBoard
from freipose.calibration.detect import CameraDetections
from freipose.calibration.intrinsics import CalibrationError
from freipose.calibration.options import CalibrationOptions
from freipose.calibration.params import RVEC
from freipose.calibration.pipeline import calibrate_detections
from freipose.calibration.plausibility import (
    ImplausibleCalibrationError,
    check_plausibility,
    fold_pixel_radius,
    folding_radius,
    folding_warnings,
)
from freipose.testing import make_circle_rig

BOARD = CharucoBoard(8, 6, 40.0, 30.0, "DICT_4X4_50")
OPT = CalibrationOptions(progress=False)
FORCE = CalibrationOptions(progress=False, accept_implausible=True)
DIAG = float(np.hypot(*BOARD.size_mm))


@pytest.fixture(scope="module")
def rig():
    return make_circle_rig(4, radius=700.0, height=400.0, distortion=True)


@pytest.fixture(scope="module")
def dets(rig):
    return board_detections(rig, BOARD.object_points, BOARD.size_mm, 80, noise_px=0.2)[0]


@pytest.fixture(scope="module")
def result(dets):
    return calibrate_detections(dets, BOARD, OPT)


def _replaced(dets, i, points):
    out = list(dets)
    out[i] = CameraDetections(dets[i].name, dets[i].size, points)
    return out


def _check(result, cam_params=None, inliers=None):
    ba = result.bundle
    ba = dataclasses.replace(
        ba,
        cam_params=ba.cam_params if cam_params is None else cam_params,
        inliers=ba.inliers if inliers is None else inliers,
    )
    names = [d.name for d in result.detections]
    sizes = [d.size for d in result.detections]
    return check_plausibility(names, sizes, ba, DIAG, result.standard_errors)


def test_ordinary_rig_is_plausible(result):
    assert result.findings == ()
    assert "suspect" not in result.rig.metadata
    assert _check(result) == ()


def test_mirrored_camera_refused(dets):
    p = dets[1].points.copy()
    p[..., 0] = dets[1].size[0] - 1 - p[..., 0]
    with pytest.raises(ImplausibleCalibrationError, match="camera cam1: .*rejected") as e:
        calibrate_detections(_replaced(dets, 1, p), BOARD, OPT)
    assert "--fix-intrinsics" in str(e.value) and "--force" in str(e.value)
    assert any(f.camera == "cam1" and f.check == "outliers" for f in e.value.findings)


def test_unsynchronized_camera_refused_unless_forced(dets):
    bad = _replaced(dets, 1, np.roll(dets[1].points, 3, axis=0))
    with pytest.raises(ImplausibleCalibrationError, match="camera cam1"):
        calibrate_detections(bad, BOARD, OPT)
    res = calibrate_detections(bad, BOARD, FORCE)
    assert any(f.camera == "cam1" for f in res.findings)
    assert [f["camera"] for f in res.rig.metadata["suspect"]] == [f.camera for f in res.findings]


def test_camera_with_three_frames_refused(dets):
    p = dets[1].points.copy()
    seen = np.flatnonzero(np.isfinite(p[:, :, 0]).sum(1) >= 6)
    p[seen[3:]] = np.nan
    with pytest.raises(CalibrationError, match="camera cam1: only 3 frame.*--fix-intrinsics"):
        calibrate_detections(_replaced(dets, 1, p), BOARD, OPT)


def test_board_poses_disagree(result):
    cam = result.bundle.cam_params.copy()
    cam[2, RVEC] += np.radians([0.0, 12.0, 0.0])  # cam2 turned by 12 degrees
    found = _check(result, cam_params=cam)
    assert [(f.camera, f.check) for f in found] == [("cam2", "board_poses")]
    assert "degrees" in found[0].message


def test_rig_misfit(result):
    """Detections the rig explains much worse than the camera alone: refused, not rejected."""
    from freipose.calibration.bundle_problem import project_observations

    ba = result.bundle
    cam = ba.cam_params.copy()
    cam[2, RVEC] += np.radians([0.0, 0.4, 0.0])  # cam2 turned by 0.4 degrees: a few px off
    uv, _ = project_observations(cam, ba.frame_params, ba.obs)
    off = dataclasses.replace(ba, cam_params=cam, errors=np.linalg.norm(uv - ba.obs.uv, axis=1))
    names = [d.name for d in result.detections]
    sizes = [d.size for d in result.detections]
    own = {n: r.rms for n, r in result.intrinsics.items()}
    found = check_plausibility(names, sizes, off, DIAG, result.standard_errors, own_rms=own)
    assert [(f.camera, f.check) for f in found] == [("cam2", "rig_misfit")]
    assert "a camera of their own at 0.2" in found[0].message
    assert check_plausibility(names, sizes, ba, DIAG, result.standard_errors, own_rms=own) == ()


def test_focal_principal_point_and_folding(result):
    cam = result.bundle.cam_params.copy()
    cam[0, :2] = 6.7  # the focal length
    cam[1, 2] = -300.0  # principal point far left of a 640 px image
    cam[3, 4:9] = [-1.5, 0.0, 0.0, 0.0, 0.0]  # folds at r = 0.47 < the corner's 0.5
    found = {(f.camera, f.check) for f in _check(result, cam_params=cam)}
    assert {("cam0", "field_of_view"), ("cam1", "principal_point")} <= found
    assert ("cam3", "folding_distortion") in found
    msg = " ".join(f.message for f in _check(result, cam_params=cam))
    assert "177.6 degrees" in msg and "(-300.0, " in msg


def test_outlier_share(result):
    keep = result.bundle.inliers.copy()
    mine = np.flatnonzero(result.bundle.obs.cam == 3)
    keep[mine[: int(0.4 * mine.size)]] = False
    found = _check(result, inliers=keep)
    assert [(f.camera, f.check) for f in found] == [("cam3", "outliers")]


def test_fold_beyond_the_board_is_a_warning(result):
    """A fold only beyond the board's reach warns; the same fold inside it is refused."""
    ba = result.bundle
    cam = ba.cam_params.copy()
    cam[3, 4:9] = [-1.5, 0.0, 0.0, 0.0, 0.0]  # folds at distorted radius 0.314
    p = cam[3]
    rad = np.hypot((ba.obs.uv[:, 0] - p[2]) / p[0], (ba.obs.uv[:, 1] - p[3]) / p[1])
    mine = ba.obs.cam == 3
    assert rad[mine & ba.inliers].max() > 0.35  # the board reached beyond the fold
    near = ba.inliers & ~(mine & (rad > 0.2))  # camera 3's board only within radius 0.2
    names = [d.name for d in result.detections]
    sizes = [d.size for d in result.detections]
    found = _check(result, cam_params=cam, inliers=near)
    assert ("cam3", "folding_distortion") not in {(f.camera, f.check) for f in found}
    warned = folding_warnings(names, sizes, dataclasses.replace(ba, cam_params=cam, inliers=near))
    assert len(warned) == 1 and warned[0].startswith("camera cam3: ")
    assert "coverage_cam3.png" in warned[0] and "folds " in warned[0] and "(0.314)" in warned[0]
    found = _check(result, cam_params=cam)
    assert ("cam3", "folding_distortion") in {(f.camera, f.check) for f in found}
    assert folding_warnings(names, sizes, dataclasses.replace(ba, cam_params=cam)) == []


def test_fold_pixel_radius_and_its_circle_in_the_coverage_map():
    from freipose.calibration.report import _coverage_map

    K = np.array([[200.0, 0, 159.5], [0, 200.0, 127.5], [0, 0, 1]])
    assert fold_pixel_radius(K, np.array([-0.2, 0.04, 0, 0, 0]), (320, 256)) is None
    r = fold_pixel_radius(K, np.array([-1.5, 0, 0, 0, 0]), (320, 256))
    assert r == pytest.approx(200 * np.sqrt(1 / 4.5) * 2 / 3, rel=2e-3)
    det = CameraDetections("cam0", (320, 256), np.full((1, 4, 2), np.nan))
    fig = _coverage_map(det, None, (159.5, 127.5, r))
    lines = fig.axes[0].get_lines()
    assert [ln.get_label() for ln in lines] == ["the lens model folds beyond"]
    assert np.hypot(lines[0].get_xdata() - 159.5, lines[0].get_ydata() - 127.5) == (
        pytest.approx(r)
    )


def test_folding_radius():
    assert folding_radius(np.zeros(5), 0.8) is None
    assert folding_radius(np.array([-0.12, 0.05, 0, 0, -0.01]), 0.5) is None
    r = folding_radius(np.array([-1.5, 0, 0, 0, 0]), 0.5)
    assert r == pytest.approx(np.sqrt(1 / 4.5), abs=1e-3)


def test_standard_errors(rig, dets, result):
    more = board_detections(rig, BOARD.object_points, BOARD.size_mm, 240, noise_px=0.2)[0]
    big = calibrate_detections(more, BOARD, OPT)
    inside = 0
    for cam, truth in zip(result.rig, rig):
        se = result.standard_errors[cam.name]
        assert se["fx"] > 0 and se["fy"] == se["fx"] and se["k1"] > 0 and se["k2"] > 0
        assert big.standard_errors[cam.name]["fx"] < se["fx"]
        assert big.standard_errors[cam.name]["k1"] < se["k1"]
        inside += abs(cam.K[0, 0] - truth.K[0, 0]) < 3 * se["fx"]
    # (with fy tied to fx the covariance must use the tie: fixing fy instead made the
    # standard errors 4 times too small)
    assert inside >= 3
    md = result.rig.metadata["intrinsics_standard_errors"]
    assert md["cam0"]["fx"] == pytest.approx(result.standard_errors["cam0"]["fx"], rel=1e-3)


def test_cli_refuses_and_force_marks_suspect(tmp_path, dets, monkeypatch):
    from freipose.calibration import pipeline
    from freipose.cli.main import cli

    p = dets[1].points.copy()
    p[..., 0] = dets[1].size[0] - 1 - p[..., 0]
    bad = _replaced(dets, 1, p)
    monkeypatch.setattr(pipeline, "detect_cameras", lambda *a, **k: bad)
    inputs = []
    for d in bad:
        (tmp_path / d.name).mkdir()
        inputs.append(str(tmp_path / d.name))
    out, rep = tmp_path / "calibration.toml", tmp_path / "report"
    args = ["calib", "run", *inputs, "--board-type", "charuco", "--squares-x", "8"]
    args += ["--squares-y", "6", "--square-size", "40", "--marker-size", "30"]
    args += ["--dictionary", "DICT_4X4_50", "-o", str(out), "--report", str(rep)]
    r = CliRunner().invoke(cli, args, catch_exceptions=False)
    assert r.exit_code != 0
    assert "camera cam1" in r.output and "not physically plausible" in r.output
    assert not out.exists() and not rep.exists()
    r = CliRunner().invoke(cli, [*args, "--force"], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    assert "SUSPECT" in r.output and "marked as suspect" in r.output
    suspect = tomllib.loads(out.read_text())["metadata"]["suspect"]
    assert any(f["camera"] == "cam1" for f in suspect)
    summary = json.loads((rep / "summary.json").read_text())
    assert any(f["camera"] == "cam1" for f in summary["suspect"])
    assert summary["cameras"]["cam0"]["intrinsics_standard_errors"]["fx"] > 0
    r = CliRunner().invoke(cli, ["calib", "show", str(out)], catch_exceptions=False)
    assert "SUSPECT" in r.output and "standard errors" in r.output


def test_wrong_given_intrinsics_refused(rig, dets):
    from freipose.geometry import Camera, CameraRig

    cams = list(rig)
    c = cams[1]
    K = c.K.copy()
    K[:2, :2] *= 1.2  # the --fix-intrinsics file of another lens
    cams[1] = Camera(c.name, c.size, K, c.dist, c.R, c.t)
    opt = CalibrationOptions(progress=False, fixed_intrinsics=CameraRig(tuple(cams)))
    with pytest.raises(ImplausibleCalibrationError, match="camera cam1: .*intrinsics were given"):
        calibrate_detections(dets, BOARD, opt)
