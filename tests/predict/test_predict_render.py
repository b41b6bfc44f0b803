"""Overlay rendering: grid layout, projected keypoints coloured by confidence, frame ranges."""

from __future__ import annotations

import cv2
import numpy as np
from click.testing import CliRunner
from predict_helpers import BlobEstimator, make_session

from freipose.cli.main import cli
from freipose.io.poses import read_poses_h5
from freipose.io.session import discover_sessions
from freipose.predict.render import confidence_color
from freipose.predict.run import predict_session


def test_confidence_colors():
    assert confidence_color(0.0) == (0, 0, 255)
    assert confidence_color(1.0) == (0, 255, 0)
    assert confidence_color(0.5) == (0, 255, 255)
    assert confidence_color(float("nan")) == (0, 0, 255)


def test_render_command(tmp_path):
    folder = tmp_path / "rec"
    make_session(folder, 12, absent=(4,))
    (s,) = discover_sessions([folder])
    poses = predict_session(s, BlobEstimator(), tmp_path, batch_size=4, progress=False).path
    out = tmp_path / "overlay.mkv"
    args = ["render", str(folder), str(poses), "-o", str(out), "--frames", "2:10",
            "--cameras", "cam2,cam0", "--tile-width", "160"]  # fmt: skip
    res = CliRunner().invoke(cli, args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    cap = cv2.VideoCapture(str(out))
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(f)
    assert len(frames) == 8
    assert frames[0].shape == (240, 320, 3)  # 2 x 2 grid of 160 x 120 tiles (2 views + 3D)
    d = read_poses_h5(poses)
    # frame 3: keypoint "red" of camera cam2 (first tile) is drawn in the colour of its
    # confidence (1 -> green) at its projection
    uv = d.calibration.project(d.poses[3].astype(np.float64))[d.calibration.index("cam2"), 0]
    x, y = int(round(uv[0])), int(round(uv[1]))
    assert d.confidence[3, 0] == 1.0
    patch = frames[1][y - 1 : y + 2, x - 1 : x + 2].reshape(-1, 3).astype(int)
    assert np.any((patch[:, 1] > 200) & (patch[:, 2] < 80) & (patch[:, 0] < 80)), patch
    # the 3D panel (bottom left) is not empty
    assert frames[1][120:, :160].std() > 5
    res = CliRunner().invoke(cli, ["render", str(folder), str(poses), "-o", str(out),
                                   "--cameras", "side"])  # fmt: skip
    assert res.exit_code != 0 and "side" in res.output
    res = CliRunner().invoke(cli, ["render", str(folder), str(poses), "-o", str(out),
                                   "--frames", "50:60"])  # fmt: skip
    assert res.exit_code != 0 and "selects no frames" in res.output
