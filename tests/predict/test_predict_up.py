"""predict writes the calibration's up direction into the poses; without one, the up the
predicted animal gives (the plane it moves on), and world z only when nothing gives one."""

from __future__ import annotations

import logging

import cv2
import numpy as np
from predict_helpers import BlobEstimator, make_session

from freipose.geometry import CameraRig
from freipose.io.calibration import save_calibration
from freipose.io.calibration_world import WorldUp, with_world_up
from freipose.io.poses import read_poses_h5
from freipose.io.session import discover_sessions
from freipose.predict.run import predict_session


def _tilted(rig: CameraRig, Q: np.ndarray) -> CameraRig:
    """The same cameras in a world rotated by Q (X' = Q X)."""
    cams = tuple(c.replace(R=c.R @ Q.T) for c in rig)
    return CameraRig(cams, dict(rig.metadata))


def test_poses_up_comes_from_the_calibration_else_from_the_predicted_animal(tmp_path, caplog):
    folder = tmp_path / "rec"
    rig, _ = make_session(folder, 64)  # a full circle over the floor
    Q = cv2.Rodrigues(np.array([0.5, -0.3, 0.2]))[0]
    save_calibration(_tilted(rig, Q), folder / "calibration.toml")
    with caplog.at_level(logging.WARNING):
        (s,) = discover_sessions([folder])
        est = predict_session(s, BlobEstimator(), tmp_path / "a", batch_size=4, progress=False)
    got = read_poses_h5(est.path).up
    # the blobs move over the plane z = const of the videos' world: Q z in the tilted one
    assert np.degrees(np.arccos(np.clip(got @ (Q @ [0, 0, 1]), -1, 1))) < 3.0
    assert "estimated from" in caplog.text and "predicted 3D points" in caplog.text
    import h5py

    with h5py.File(est.path, "r") as f:
        assert "predicted 3D points" in str(f.attrs["up_source"])
    # too few points: world z, said in a warning
    caplog.clear()
    still = tmp_path / "still"
    make_session(still, 8, absent=tuple(range(8)))
    with caplog.at_level(logging.WARNING):
        (s,) = discover_sessions([still])
        plain = predict_session(s, BlobEstimator(), tmp_path / "b", batch_size=4, progress=False)
    np.testing.assert_allclose(read_poses_h5(plain.path).up, [0, 0, 1])
    assert "assumes world z is up" in caplog.text
    # a stored up is written as it is
    up = np.array([0.0, -0.6, 0.8])
    save_calibration(with_world_up(rig, WorldUp(up, "given")), folder / "calibration.toml")
    (s,) = discover_sessions([folder])
    got = predict_session(s, BlobEstimator(), tmp_path / "c", batch_size=4, progress=False)
    np.testing.assert_allclose(read_poses_h5(got.path).up, up)
