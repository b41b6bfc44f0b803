"""A calibration.toml camera's rotation: a Rodrigues vector or a 3x3 rotation matrix."""

from __future__ import annotations

import numpy as np
import pytest
import tomli_w

from freipose.io.calibration import load_calibration
from freipose.io.calibration_toml import CalibrationFormatError, rig_to_toml_dict
from freipose.testing import make_circle_rig


def _write(tmp_path, rotation):
    rig = make_circle_rig(2)
    data = rig_to_toml_dict(rig)
    data["cam_1"]["rotation"] = rotation(rig[1].R)
    p = tmp_path / "calibration.toml"
    p.write_text(tomli_w.dumps(data))
    return rig, p


def test_a_3x3_rotation_matrix_is_read(tmp_path):
    rig, p = _write(tmp_path, lambda R: R.tolist())
    got = load_calibration(p)
    np.testing.assert_allclose(got[1].R, rig[1].R, atol=1e-12)
    np.testing.assert_allclose(got[0].R, rig[0].R, atol=1e-12)
    # written with 4 digits: the nearest rotation
    rig, p = _write(tmp_path, lambda R: np.round(R, 4).tolist())
    got = load_calibration(p)
    np.testing.assert_allclose(got[1].R, rig[1].R, atol=1e-3)
    assert np.abs(got[1].R @ got[1].R.T - np.eye(3)).max() < 1e-12


@pytest.mark.parametrize(
    "rotation, message",
    [
        (lambda R: (R * [1, 1, -1]).tolist(), r"not a rotation matrix .*determinant -1"),
        (lambda R: (R * 1.1).tolist(), r"not a rotation matrix \(R R\^T differs"),
        (lambda R: R[:2].tolist(), r"\[cam_1\] \(camera 'cam1'\): rotation must be a Rodrigues"),
        (lambda R: [0.1, 0.2], r"3x3 rotation matrix \(world->camera\), got shape \(2,\)"),
        (lambda R: [[1, 0, 0], [0, 1], [0, 0, 1]], r"rotation must be a Rodrigues vector"),
    ],
)
def test_other_rotations_are_refused_naming_the_camera(tmp_path, rotation, message):
    _, p = _write(tmp_path, rotation)
    with pytest.raises(CalibrationFormatError, match=message) as e:
        load_calibration(p)
    assert "cam1" in str(e.value)
