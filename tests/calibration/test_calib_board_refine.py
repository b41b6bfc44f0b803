"""Board-point refinement: per-point offsets of the printed board estimated in the adjustment."""

from __future__ import annotations

import numpy as np
import pytest
from calib_helpers import board_detections, rig_errors

from freipose.calibration.boards import CharucoBoard
from freipose.calibration.detect import CameraDetections
from freipose.calibration.options import CalibrationOptions
from freipose.calibration.pipeline import calibrate_detections
from freipose.testing import make_circle_rig

BOARD = CharucoBoard(6, 5, 40.0, 30.0, "DICT_4X4_50")


def _similarity_free(offsets: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """``offsets`` (P, 2) without translation, rotation and scale about the centroid of xy."""
    x = xy - xy.mean(axis=0)
    P = len(x)
    basis = np.stack(
        [np.tile([1.0, 0], P), np.tile([0, 1.0], P), np.c_[-x[:, 1], x[:, 0]].ravel(), x.ravel()],
        axis=1,
    )
    q, _ = np.linalg.qr(basis)
    v = offsets.ravel()
    return (v - q @ (q.T @ v)).reshape(P, 2)


@pytest.fixture(scope="module")
def warped():
    # the printed board's points are off their design positions by ~0.15 mm (what a detector's
    # per-corner bias or a print does); the detections see the true points
    rig = make_circle_rig(4, radius=700.0, height=400.0, distortion=True)
    rng = np.random.default_rng(7)
    obj = BOARD.object_points
    true_off = _similarity_free(rng.normal(0, 0.15, (len(obj), 2)), obj[:, :2])
    printed = obj.copy()
    printed[:, :2] += true_off
    dets, _ = board_detections(rig, printed, BOARD.size_mm, 150, noise_px=0.05, seed=2)
    return rig, dets, true_off


def test_board_offsets_recovered_and_rig_improves(warped):
    rig, dets, true_off = warped
    ref = calibrate_detections(dets, BOARD, CalibrationOptions())
    plain = calibrate_detections(dets, BOARD, CalibrationOptions(refine_board=False))
    assert plain.board_offsets is None
    off = ref.board_offsets
    # the corrections carry no translation, rotation or scale of the board (each round's is
    # free of them about the then corrected points: 1e-5 mm apart)
    xy = BOARD.object_points[:, :2]
    assert np.abs(off - _similarity_free(off, xy)).max() < 1e-4
    # they recover the printed board's deviations
    assert np.sqrt(np.mean((off - true_off) ** 2)) < 0.25 * np.sqrt(np.mean(true_off**2))
    assert ref.rig.metadata["board_point_corrections_rms_mm"] > 0.1
    dc_r, rot_r, fe_r = rig_errors(ref.rig, rig)
    dc_p, rot_p, fe_p = rig_errors(plain.rig, rig)
    assert dc_r.max() < 0.75 * dc_p.max()  # 0.20 vs 0.32 mm
    assert np.abs(fe_r).max() < 0.5 * np.abs(fe_p).max()  # 0.04 vs 0.15 %
    assert rot_r.max() < 0.9 * rot_p.max()  # 0.21 vs 0.27 deg
    assert all(s.rms < 0.1 for s in ref.stats)  # 0.05 px noise: the residuals are just noise


def test_board_offsets_need_many_views(warped):
    # 25 frames give each point fewer than 100 inlier views: no correction is attempted
    _rig, dets, _ = warped
    few = [CameraDetections(d.name, d.size, d.points[:25]) for d in dets]
    res = calibrate_detections(few, BOARD, CalibrationOptions())
    assert np.array_equal(res.board_offsets, np.zeros((len(BOARD.object_points), 2)))
