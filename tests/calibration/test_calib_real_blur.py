"""Real frames with motion blur do not drag the calibration (#19: per-view weights, real data)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from freipose.calibration.boards import ChessboardBoard
from freipose.calibration.detect import CameraDetections
from freipose.calibration.detect_videos import detect_cameras
from freipose.calibration.options import CalibrationOptions
from freipose.calibration.pipeline import calibrate_detections

BOARD = ChessboardBoard(9, 6, 30.0)


def _motion_blur(img: np.ndarray, length: int, angle: float) -> np.ndarray:
    """A centred line kernel: the board moving during the exposure, at its mid-exposure place."""
    k = np.zeros((length, length), np.float32)
    k[length // 2, :] = 1.0
    rot = cv2.getRotationMatrix2D(((length - 1) / 2, (length - 1) / 2), angle, 1.0)
    k = cv2.warpAffine(k, rot, (length, length))
    return cv2.filter2D(img, -1, k / k.sum())


@pytest.fixture
def stereo_detections(tmp_path, shared_data):
    """:func:`blurred_recording` of the real Bouguet stereo pairs."""
    return blurred_recording(tmp_path, shared_data / "opencv-bouguet-stereo" / "images")


def blurred_recording(tmp_path, src):
    """The 14 real stereo pairs, then motion-blurred copies of 6 of them, detected.

    Returns the detections and, per frame, the clean frame it is a copy of.
    """
    origin = []
    for side in ("left", "right"):
        d = tmp_path / side
        d.mkdir()
        files = sorted(src.glob(f"{side}*.jpg"))
        copies = []
        for i, f in enumerate(files):
            img = cv2.imread(str(f))
            cv2.imwrite(str(d / f"a{i:02d}.png"), img)
            if i % 2 == 0 and i < 12:
                for j, (n, ang) in enumerate([(9, 20.0), (15, 110.0)]):
                    cv2.imwrite(str(d / f"b{i:02d}_{j}.png"), _motion_blur(img, n, ang))
                    copies.append(i)
        origin = list(range(len(files))) + copies
    dets = detect_cameras([tmp_path / "left", tmp_path / "right"], BOARD, None, jobs=1,
                          progress=False)  # fmt: skip
    return dets, np.array(origin)


def _calibrate(dets):
    return calibrate_detections(dets, BOARD, CalibrationOptions(jobs=1, progress=False))


def _sharp_copies(dets, origin):
    """The detections with each blurred view replaced by its clean frame's corners."""
    out = []
    for d in dets:
        pts = d.points[origin].copy()
        pts[~d.mask.any(axis=1)] = np.nan  # the same views as the blurred ones
        out.append(CameraDetections(d.name, d.size, pts))
    return out


def test_blurred_copies_of_real_frames_leave_the_calibration_in_place(stereo_detections):
    # Copies weigh their frames' board poses more, which moves any calibration within its
    # uncertainty; the reference is therefore the same views with their sharp corners. The
    # 9 blurred views move no intrinsic by more than 2 standard errors (measured: f up to
    # 0.15 px = 0.7, the principal point up to 0.52 px = 1.6) nor the baseline by 0.05 mm
    # (measured: 0.02 mm).
    dets, origin = stereo_detections
    blurred = np.arange(len(origin)) >= 14
    found = dets[0].mask.any(axis=1) & dets[1].mask.any(axis=1) & blurred
    assert found.sum() >= 6  # the blurred views are found, so they take part
    with_blur = _calibrate(dets)
    sharp = _calibrate(_sharp_copies(dets, origin))
    for cam in ("left", "right"):
        se = sharp.standard_errors[cam]
        a, b = sharp.rig[cam].K, with_blur.rig[cam].K
        assert abs(b[0, 0] - a[0, 0]) < 2 * se["fx"], (cam, a[0, 0], b[0, 0], se)
        assert abs(b[0, 2] - a[0, 2]) < 2 * se["cx"] and abs(b[1, 2] - a[1, 2]) < 2 * se["cy"]
        assert abs(with_blur.rig[cam].dist[0] - sharp.rig[cam].dist[0]) < 2 * se["k1"]
    length = [np.linalg.norm(r.rig["right"].center) for r in (sharp, with_blur)]
    assert abs(length[1] - length[0]) < 0.05  # mm, of a 99.8 mm baseline
