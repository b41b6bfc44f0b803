"""predict writes the calibration's up direction into the poses (world z only when unknown)."""

from __future__ import annotations

import logging

import numpy as np
from predict_helpers import BlobEstimator, make_session

from freipose.io.calibration import save_calibration
from freipose.io.calibration_world import WorldUp, with_world_up
from freipose.io.poses import read_poses_h5
from freipose.io.session import discover_sessions
from freipose.predict.run import predict_session


def test_poses_up_comes_from_the_calibration(tmp_path, caplog):
    folder = tmp_path / "rec"
    rig, _ = make_session(folder, 4)
    with caplog.at_level(logging.WARNING):
        (s,) = discover_sessions([folder])
        plain = predict_session(s, BlobEstimator(), tmp_path / "a", batch_size=4, progress=False)
    np.testing.assert_allclose(read_poses_h5(plain.path).up, [0, 0, 1])
    assert "assumes world z is up" in caplog.text
    up = np.array([0.0, -0.6, 0.8])
    save_calibration(with_world_up(rig, WorldUp(up, "given")), folder / "calibration.toml")
    (s,) = discover_sessions([folder])
    got = predict_session(s, BlobEstimator(), tmp_path / "b", batch_size=4, progress=False)
    np.testing.assert_allclose(read_poses_h5(got.path).up, up)
