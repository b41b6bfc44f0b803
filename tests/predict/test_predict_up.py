"""predict writes the calibration's up direction into the poses; without one, the up the
predicted animal determines (the plane it moves on), flagged as estimated, and world z
(flagged as assumed) when the frames do not determine it; shards estimate nothing."""

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


def test_poses_up_comes_from_the_calibration_else_is_flagged_as_assumed(tmp_path, caplog):
    folder = tmp_path / "rec"
    rig, _ = make_session(folder, 64)  # one circle, the blobs bobbing up and down by 40 mm
    Q = cv2.Rodrigues(np.array([0.5, -0.3, 0.2]))[0]
    save_calibration(_tilted(rig, Q), folder / "calibration.toml")
    with caplog.at_level(logging.WARNING):
        (s,) = discover_sessions([folder])
        est = predict_session(s, BlobEstimator(), tmp_path / "a", batch_size=4, progress=False)
    # 64 frames do not determine the up to within a few degrees: not stored as a fact
    np.testing.assert_allclose(read_poses_h5(est.path).up, [0, 0, 1])
    assert "determine it only to within" in caplog.text and "assumes world z" in caplog.text
    import h5py

    with h5py.File(est.path, "r") as f:
        assert str(f.attrs["up_source"]).startswith("assumed")
    # a stored up is written as it is
    up = np.array([0.0, -0.6, 0.8])
    save_calibration(with_world_up(rig, WorldUp(up, "given")), folder / "calibration.toml")
    (s,) = discover_sessions([folder])
    got = predict_session(s, BlobEstimator(), tmp_path / "c", batch_size=4, progress=False)
    np.testing.assert_allclose(read_poses_h5(got.path).up, up)


def test_shards_store_no_up_of_their_own_and_merge_estimates_it(tmp_path):
    import h5py

    from freipose.predict.merge import merge_outputs

    folder = tmp_path / "rec"
    rig, _ = make_session(folder, 48)
    Q = cv2.Rodrigues(np.array([0.5, -0.3, 0.2]))[0]
    save_calibration(_tilted(rig, Q), folder / "calibration.toml")
    (s,) = discover_sessions([folder])
    parts = [
        predict_session(s, BlobEstimator(), tmp_path / "sh", batch_size=4, chunk_frames=8,
                        shard=(i, 2), progress=False).path
        for i in range(2)
    ]  # fmt: skip
    for p in parts:  # the same up in every shard, flagged as unknown
        with h5py.File(p, "r") as f:
            np.testing.assert_array_equal(f.attrs["up"], [0, 0, 1])
            assert str(f.attrs["up_source"]).startswith("unknown")
    (merged,) = merge_outputs([tmp_path / "sh"], tmp_path / "merged")
    with h5py.File(merged, "r") as f:  # 48 frames determine no up: assumed, and said so
        assert str(f.attrs["up_source"]).startswith("assumed")
