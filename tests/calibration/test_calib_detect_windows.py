"""ChArUco detection with two adaptive-threshold windows finds what OpenCV's default finds."""

from __future__ import annotations

import numpy as np
import pytest
from calib_helpers import rendered_view


def test_two_threshold_windows_match_default_detection():
    cv2 = pytest.importorskip("cv2")
    from freipose.calibration.detect import CHARUCO_THRESH_WINDOWS, detect_image
    from freipose.geometry import project

    rig, board, poses, images = rendered_view(0, 60, 3, slice(8, None, 4))  # board in the air
    cp = cv2.aruco.CharucoParameters()
    cp.minMarkers = 2
    dp = cv2.aruco.DetectorParameters()  # OpenCV's default windows 3, 13, 23 px
    assert dp.adaptiveThreshWinSizeMax > CHARUCO_THRESH_WINDOWS[1]
    reference = cv2.aruco.CharucoDetector(board.cv_board(), cp, dp)
    n_ours = n_ref = 0
    errors = []
    for image, pose in zip(images, poses):
        ids, pts = detect_image(image, board)
        cc, ci, _, _ = reference.detectBoard(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))
        ref_ids = np.zeros(0, int) if ci is None else np.asarray(ci).reshape(-1)
        n_ours, n_ref = n_ours + len(ids), n_ref + len(ref_ids)
        truth = project(board.object_points @ pose[:3, :3].T + pose[:3, 3], rig[0])
        errors.append(np.linalg.norm(pts - truth[ids], axis=1))
    errors = np.concatenate(errors)
    assert n_ref > 60  # the board is seen in most frames
    assert n_ours >= 0.97 * n_ref
    assert np.median(errors) < 0.1 and np.percentile(errors, 90) < 0.5
