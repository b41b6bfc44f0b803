"""Robust scale from the noise, covariance and model selection of the bundle adjustment."""

from __future__ import annotations

import numpy as np
import pytest
from calib_helpers import board_detections, rig_errors

from freipose.calibration.boards import CharucoBoard
from freipose.calibration.options import CalibrationOptions
from freipose.calibration.pipeline import CalibrationError, calibrate_detections
from freipose.calibration.robust import noise_sigma
from freipose.testing import make_circle_rig

BOARD = CharucoBoard(8, 6, 40.0, 30.0, "DICT_4X4_50")


def _with_offsets(rig, offsets, tangential, aspects):
    cams = []
    for cam, (dx, dy), (p1, p2), a in zip(rig, offsets, tangential, aspects):
        K = cam.K.copy()
        K[1, 1] = a * K[0, 0]
        K[0, 2] = (cam.width - 1) / 2 + dx
        K[1, 2] = (cam.height - 1) / 2 + dy
        dist = np.array([-0.08, 0.02, p1, p2, 0.0])
        cams.append(cam.replace(K=K, dist=dist))
    return type(rig)(tuple(cams), rig.metadata)


@pytest.fixture(scope="module")
def mixed_rig():
    # cam0, cam1: principal point at the centre, no tangential terms; cam1: fy = 1.01 fx;
    # cam2: 12 px offset; cam3: tangential distortion
    rig = make_circle_rig(4, radius=700.0, height=400.0, distortion=False)
    return _with_offsets(
        rig,
        [(0, 0), (0, 0), (12.0, -9.0), (0, 0)],
        [(0, 0), (0, 0), (0, 0), (0.004, -0.003)],
        [1.0, 1.01, 1.0, 1.0],
    )


@pytest.fixture(scope="module")
def mixed_result(mixed_rig):
    dets, _ = board_detections(mixed_rig, BOARD.object_points, BOARD.size_mm, 120, 0.1, seed=3)
    return calibrate_detections(dets, BOARD, CalibrationOptions())


def test_model_selection_keeps_what_the_data_show(mixed_result, mixed_rig):
    models = mixed_result.rig.metadata["intrinsics_model"]
    assert models["cam0"] == {
        "principal_point": "image centre",
        "distortion": "k1 k2",
        "focal": "fx = fy",
    }
    assert models["cam1"]["principal_point"] == "image centre"
    assert models["cam1"]["focal"] == "fx, fy"
    assert [models[f"cam{i}"]["focal"] for i in (2, 3)] == ["fx = fy", "fx = fy"]
    assert models["cam2"]["principal_point"] == "estimated"
    assert models["cam3"]["distortion"] == "k1 k2 p1 p2"
    est = mixed_result.rig
    assert est["cam0"].K[0, 2] == (est["cam0"].width - 1) / 2
    assert est["cam0"].K[0, 0] == est["cam0"].K[1, 1]
    assert abs(est["cam1"].K[1, 1] / est["cam1"].K[0, 0] - 1.01) < 1e-3
    assert np.allclose(est["cam2"].K[:2, 2], mixed_rig["cam2"].K[:2, 2], atol=1.0)
    assert np.allclose(est["cam3"].dist[2:4], [0.004, -0.003], atol=5e-4)
    assert est["cam0"].dist[2] == 0.0 and est["cam0"].dist[3] == 0.0
    dc, rot, fe = rig_errors(est, mixed_rig)
    assert dc.max() < 1.0 and rot.max() < 0.1 and np.abs(fe).max() < 0.3


def test_free_model_estimates_everything(mixed_rig):
    dets, _ = board_detections(mixed_rig, BOARD.object_points, BOARD.size_mm, 60, 0.1, seed=4)
    res = calibrate_detections(
        dets,
        BOARD,
        CalibrationOptions(dist_model="k1k2p", principal_point="free", aspect="free"),
    )
    models = res.rig.metadata["intrinsics_model"]
    free = {"principal_point": "estimated", "distortion": "k1 k2 p1 p2", "focal": "fx, fy"}
    assert all(m == free for m in models.values())
    assert all(c.K[0, 2] != (c.width - 1) / 2 for c in res.rig)
    assert all(c.K[0, 0] != c.K[1, 1] for c in res.rig)
    fixed = calibrate_detections(
        dets, BOARD, CalibrationOptions(principal_point="centre", aspect="square")
    )
    assert all(c.K[0, 2] == (c.width - 1) / 2 for c in fixed.rig)
    assert all(c.K[0, 0] == c.K[1, 1] for c in fixed.rig)  # even cam1's (fy = 1.01 fx)
    with pytest.raises(CalibrationError, match="principal_point"):
        calibrate_detections(dets, BOARD, CalibrationOptions(principal_point="middle"))
    with pytest.raises(CalibrationError, match="aspect"):
        calibrate_detections(dets, BOARD, CalibrationOptions(aspect="round"))


def test_robust_scale_follows_the_noise(mixed_result):
    # 0.1 px of noise per axis: the loss scale is ~2 sigma, not the old fixed 1 px
    ba = mixed_result.bundle
    assert 0.1 < ba.f_scale < 0.35
    sigma = noise_sigma(ba.errors[ba.inliers])
    assert 0.08 < sigma < 0.12


def test_noise_sigma_of_rayleigh_errors(rng):
    e = np.linalg.norm(rng.normal(0, 0.3, (20000, 2)), axis=1)
    e[:500] = 50.0  # outliers do not move the median much
    assert abs(noise_sigma(e) - 0.3) < 0.02
    assert np.isnan(noise_sigma(np.array([np.nan])))
