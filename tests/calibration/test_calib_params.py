"""The bundle adjustment's parameter layout: named slices and the camera pack/unpack pair."""

from __future__ import annotations

import numpy as np
import pytest

from freipose.calibration.intrinsics import CalibrationError
from freipose.calibration.params import (
    CAM_PARAMS,
    DIST,
    EXTRINSICS,
    FOCAL,
    FRAME_PARAMS,
    FRAME_RVEC,
    FRAME_TVEC,
    INTRINSICS,
    PINHOLE,
    PRINCIPAL,
    RVEC,
    TANGENTIAL,
    TVEC,
    camera_to_params,
    params_to_camera,
)
from freipose.testing import make_circle_rig


def test_slices_cover_the_rows_in_order():
    cols = np.arange(CAM_PARAMS)
    assert list(cols[FOCAL]) + list(cols[PRINCIPAL]) == list(cols[PINHOLE])
    assert list(cols[PINHOLE]) + list(cols[DIST]) == list(cols[INTRINSICS])
    assert list(cols[RVEC]) + list(cols[TVEC]) == list(cols[EXTRINSICS])
    assert list(cols[INTRINSICS]) + list(cols[EXTRINSICS]) == list(cols)
    assert list(cols[TANGENTIAL]) == [6, 7]  # p1 p2 inside (k1, k2, p1, p2, k3)
    fcols = np.arange(FRAME_PARAMS)
    assert list(fcols[FRAME_RVEC]) + list(fcols[FRAME_TVEC]) == list(fcols)


def test_camera_round_trip():
    for cam in make_circle_rig(3, distortion=True):
        p = camera_to_params(cam)
        assert p.shape == (CAM_PARAMS,)
        np.testing.assert_array_equal(p[FOCAL], [cam.K[0, 0], cam.K[1, 1]])
        np.testing.assert_array_equal(p[PRINCIPAL], [cam.K[0, 2], cam.K[1, 2]])
        np.testing.assert_array_equal(p[DIST], cam.dist)
        np.testing.assert_array_equal(p[TVEC], cam.t)
        back = params_to_camera(cam.name, cam.size, p)
        assert back.allclose(cam, atol=1e-12)


def test_skew_is_refused():
    cam = make_circle_rig(2)[0]
    K = cam.K.copy()
    K[0, 1] = 0.5
    with pytest.raises(CalibrationError, match="skew"):
        camera_to_params(cam.replace(K=K))
