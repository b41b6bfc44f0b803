"""Calibration solver on exactly projected board detections (fast; no images)."""

from __future__ import annotations

import numpy as np
import pytest
from calib_helpers import board_detections, rig_errors

from freipose.calibration.boards import CharucoBoard
from freipose.calibration.bundle import bundle_adjust
from freipose.calibration.detect import CameraDetections
from freipose.calibration.extrinsics import connected_groups
from freipose.calibration.intrinsics import CalibrationError, calibrate_intrinsics, select_views
from freipose.calibration.options import CalibrationOptions
from freipose.calibration.pipeline import calibrate_detections
from freipose.testing import make_circle_rig

BOARD = CharucoBoard(8, 6, 40.0, 30.0, "DICT_4X4_50")


@pytest.fixture(scope="module")
def rig():
    return make_circle_rig(4, radius=700.0, height=400.0, distortion=True)


@pytest.fixture(scope="module")
def dets(rig):
    return board_detections(rig, BOARD.object_points, BOARD.size_mm, 150, noise_px=0.2)[0]


@pytest.fixture(scope="module")
def result(dets):
    return calibrate_detections(dets, BOARD, CalibrationOptions(dist_model="full"))


def test_recovers_rig(result, rig):
    dc, rot, fe = rig_errors(result.rig, rig)
    assert dc.max() < 2.0, dc
    assert rot.max() < 0.2, rot
    assert np.abs(fe).max() < 0.5, fe
    for s in result.stats:
        assert 0.2 < s.rms < 0.4  # noise is 0.2 px per axis: RMS norm ~0.28
    assert "camera cam0's frame" in result.rig.metadata["world"]
    assert np.allclose(result.rig[0].R, np.eye(3)) and np.allclose(result.rig[0].t, 0)


@pytest.mark.slow
def test_scipy_solver_agrees(dets, rig):
    # the cross-check solver (scipy least_squares) reaches the same optimum from the same start
    few = [CameraDetections(d.name, d.size, d.points[:40]) for d in dets[:2]]
    opt = {"fixed_intrinsics": rig}
    a = calibrate_detections(few, BOARD, CalibrationOptions(**opt))
    b = calibrate_detections(few, BOARD, CalibrationOptions(solver="scipy", **opt))
    assert np.abs(a.rig.centers - b.rig.centers).max() < 0.5
    assert np.abs(a.rig.K - b.rig.K).max() < 0.5


@pytest.mark.slow
def test_square_pixels_tie_agrees_with_scipy(dets, rig):
    # fy tied to fx (square pixels): both solvers keep fx == fy exactly and reach one optimum
    few = [CameraDetections(d.name, d.size, d.points[:40]) for d in dets[:2]]
    opt = {"aspect": "square", "principal_point": "centre", "dist_model": "k1k2"}
    a = calibrate_detections(few, BOARD, CalibrationOptions(**opt))
    b = calibrate_detections(few, BOARD, CalibrationOptions(solver="scipy", **opt))
    for res in (a, b):
        assert all(c.K[0, 0] == c.K[1, 1] for c in res.rig)
        assert all(m["focal"] == "fx = fy" for m in res.rig.metadata["intrinsics_model"].values())
    assert np.abs(a.rig.centers - b.rig.centers).max() < 0.5
    assert np.abs(a.rig.K - b.rig.K).max() < 0.5
    assert np.abs(a.rig.K[:, 0, 0] / rig.K[:2, 0, 0] - 1).max() < 0.005


def test_bundle_checks_tie_and_start_inliers(result):
    ba = result.bundle
    free = np.ones_like(ba.cam_params, bool)
    C = ba.cam_params.shape[0]
    with pytest.raises(ValueError, match="equal_focal"):
        bundle_adjust(ba.cam_params, free, ba.frame_params, ba.frames, ba.obs,
                      equal_focal=np.ones(C, bool))  # fmt: skip
    with pytest.raises(ValueError, match="keep"):
        bundle_adjust(ba.cam_params, free, ba.frame_params, ba.frames, ba.obs,
                      keep=np.ones(3, bool))  # fmt: skip
    with pytest.raises(ValueError, match="view_scale"):
        bundle_adjust(ba.cam_params, free, ba.frame_params, ba.frames, ba.obs,
                      view_scale=np.ones(3))  # fmt: skip
    # starting from the previous inliers and view weights at the solution: one round,
    # nothing changes
    free[:, :9] = False  # (intrinsics fixed: the fixture's model selection fixed some)
    free[0, 9:] = False
    again = bundle_adjust(ba.cam_params, free, ba.frame_params, ba.frames, ba.obs,
                          start_f_scale=ba.f_scale, keep=ba.inliers,
                          view_scale=ba.view_scale)  # fmt: skip
    assert again.rounds == 1
    assert np.array_equal(again.inliers, ba.inliers)
    assert np.abs(again.cam_params - ba.cam_params).max() < 1e-3


def test_origin_frame_defines_floor(dets):
    # the board in the chosen frame becomes the z = 0 plane with z up out of it
    seen = np.flatnonzero(np.isfinite(dets[0].points[:, :, 0]).sum(1) > 10)
    N = int(seen[0])
    res = calibrate_detections(dets, BOARD, CalibrationOptions(origin_frame=N))
    B = res.board_poses[N]
    pts = BOARD.object_points @ B[:3, :3].T + B[:3, 3]
    assert np.abs(pts[:, 2]).max() < 1e-6
    assert np.allclose(pts[0, :2], BOARD.object_points[0, :2] * [1, -1], atol=1e-6)
    # the cameras that see the printed side in frame N are above the "floor" (z > 0)
    for i, d in enumerate(dets):
        if np.isfinite(d.points[N, :, 0]).any():
            assert res.rig.centers[i, 2] > 0
    assert res.rig.metadata["origin_frame"] == N


def test_origin_frame_without_board(dets):
    bad = [CameraDetections(d.name, d.size, d.points.copy()) for d in dets]
    for d in bad:
        d.points[3] = np.nan
    with pytest.raises(CalibrationError, match="origin-frame 3"):
        calibrate_detections(bad, BOARD, CalibrationOptions(origin_frame=3))


def test_disconnected_cameras_named(dets):
    # cam0/cam1 see the board in the first half only, cam2/cam3 in the second half
    F = dets[0].num_frames
    split = []
    for i, d in enumerate(dets):
        p = d.points.copy()
        if i < 2:
            p[F // 2 :] = np.nan
        else:
            p[: F // 2] = np.nan
        split.append(CameraDetections(d.name, d.size, p))
    with pytest.raises(CalibrationError, match=r"\{cam0, cam1\}; \{cam2, cam3\}"):
        calibrate_detections(split, BOARD)
    assert connected_groups(np.array([[0, 3, 0], [3, 0, 0], [0, 0, 0]])) == [[0, 1], [2]]


def test_too_few_frames_for_intrinsics(dets):
    p = dets[1].points.copy()
    seen = np.flatnonzero(np.isfinite(p[:, :, 0]).sum(1) >= 6)
    p[seen[3:]] = np.nan
    few = [dets[0], CameraDetections("cam1", dets[1].size, p)]
    with pytest.raises(CalibrationError, match="camera cam1: only 3 frame"):
        calibrate_detections(few, BOARD)


def test_never_detected(dets):
    empty = CameraDetections("camX", dets[0].size, np.full_like(dets[0].points, np.nan))
    with pytest.raises(CalibrationError, match="never detected in camera.*camX"):
        calibrate_detections([dets[0], empty], BOARD)


def test_fixed_and_only_intrinsics(dets, rig):
    res = calibrate_detections(dets, BOARD, CalibrationOptions(intrinsics_only=True))
    assert res.bundle is None and np.allclose(res.rig.R, np.eye(3))
    for e, g in zip(res.rig, rig):
        assert abs(e.K[0, 0] / g.K[0, 0] - 1) < 0.01
    fixed = calibrate_detections(dets, BOARD, CalibrationOptions(fixed_intrinsics=rig))
    for e, g in zip(fixed.rig, rig):
        assert np.array_equal(e.K, g.K) and np.array_equal(e.dist, g.dist)
    dc, rot, _ = rig_errors(fixed.rig, rig)
    assert dc.max() < 2.0 and rot.max() < 0.2
    with pytest.raises(CalibrationError, match="not in the --fix-intrinsics"):
        calibrate_detections(dets, BOARD, CalibrationOptions(fixed_intrinsics=rig.subset([0])))


def test_mismatched_frame_counts_use_prefix(dets):
    short = CameraDetections("cam1", dets[1].size, dets[1].points[:100])
    res = calibrate_detections([dets[0], short, dets[2], dets[3]], BOARD)
    assert all(d.num_frames == 100 for d in res.detections)
    assert any("different frame counts" in w for w in res.warnings)


def test_outliers_rejected(dets, rig):
    bad = [CameraDetections(d.name, d.size, d.points.copy()) for d in dets]
    rng = np.random.default_rng(1)
    m = np.isfinite(bad[2].points[..., 0])
    idx = np.argwhere(m)[rng.choice(int(m.sum()), 30, replace=False)]
    bad[2].points[idx[:, 0], idx[:, 1]] += rng.uniform(15, 40, (30, 2))
    res = calibrate_detections(bad, BOARD, CalibrationOptions(dist_model="full"))
    # (a perturbed frame seen by cam2 alone fails the PnP check and never enters the adjustment)
    assert (~res.bundle.inliers).sum() >= 25
    dc, rot, _ = rig_errors(res.rig, rig)
    assert dc.max() < 2.0 and rot.max() < 0.2


def test_view_selection_covers_and_tilts(dets):
    d = dets[0]
    frames, coverage, tilt = select_views(d.points, BOARD.object_points, d.size, max_views=15)
    assert 4 <= len(frames) <= 15 and coverage > 0.3 and tilt > 20
    res = calibrate_intrinsics(d.points, BOARD.object_points, d.size, "k1k2p", max_views=15)
    assert res.rms < 0.6


def test_same_detections_give_the_same_calibration(dets, result):
    # bit for bit, with one thread or several (OpenCV's multi-threaded calibrateCamera sums
    # in a varying order); the caller's OpenCV thread setting is given back
    cv2 = pytest.importorskip("cv2")
    before = cv2.getNumThreads()
    for jobs in (1, None):
        again = calibrate_detections(dets, BOARD, CalibrationOptions(dist_model="full", jobs=jobs))
        for a, b in zip(result.rig, again.rig):
            for x, y in ((a.K, b.K), (a.dist, b.dist), (a.R, b.R), (a.t, b.t)):
                np.testing.assert_array_equal(x, y)
    assert cv2.getNumThreads() == before
