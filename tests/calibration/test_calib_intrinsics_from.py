"""Intrinsics from a separate recording (``--intrinsics-from``): a calibration file."""

from __future__ import annotations

import pytest
from calib_helpers import board_detections, rig_errors

from freipose.calibration.boards import CharucoBoard
from freipose.calibration.intrinsics import CalibrationError
from freipose.calibration.options import CalibrationOptions
from freipose.calibration.pipeline import calibrate_detections, intrinsics_from
from freipose.io.calibration import save_calibration
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
