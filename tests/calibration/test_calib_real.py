"""Real images: Bouguet's stereo chessboard pairs and OpenCV's ChArUco tutorial photo."""

from __future__ import annotations

import numpy as np
import pytest

from freipose.calibration.boards import CharucoBoard, ChessboardBoard
from freipose.calibration.detect import detect_image
from freipose.calibration.detect_videos import detect_cameras
from freipose.calibration.diagnose import diagnose_board
from freipose.calibration.options import CalibrationOptions
from freipose.calibration.pipeline import calibrate


@pytest.fixture
def stereo_folders(shared_data, tmp_path):
    src = shared_data / "opencv-bouguet-stereo" / "images"
    out = {}
    for side in ("left", "right"):
        d = tmp_path / side
        d.mkdir()
        for f in sorted(src.glob(f"{side}*.jpg")):
            (d / f.name).symlink_to(f)
        out[side] = d
    return out


def test_bouguet_stereo_reproduces_published(stereo_folders, shared_data, tmp_path):
    scipy_io = pytest.importorskip("scipy.io")
    board = ChessboardBoard(9, 6, 30.0)
    res = calibrate(
        [stereo_folders["left"], stereo_folders["right"]],
        board,
        tmp_path / "stereo.toml",
        CalibrationOptions(jobs=1, progress=False),
    )
    for cam in res.rig:
        m = scipy_io.loadmat(
            shared_data
            / "opencv-bouguet-stereo"
            / "bouguet_results"
            / f"Calib_Results_{cam.name}.mat"
        )
        # Bouguet's *_error are his stated (3 sigma) uncertainties
        fc, fc_err = m["fc"].ravel(), m["fc_error"].ravel()
        cc, cc_err = m["cc"].ravel(), m["cc_error"].ravel()
        assert np.all(np.abs([cam.K[0, 0], cam.K[1, 1]] - fc) < fc_err), (cam.K, fc)
        assert np.all(np.abs([cam.K[0, 2], cam.K[1, 2]] - cc) < cc_err), (cam.K, cc)
        assert np.allclose(cam.dist[:2], m["kc"].ravel()[:2], atol=3 * m["kc_error"].ravel()[:2])
    baseline = np.linalg.norm(res.rig["right"].center - res.rig["left"].center)
    assert abs(baseline - 99.85) < 0.5, baseline
    assert all(s.rms < 0.3 for s in res.stats)
    # the detections are cached next to the output: a second run does not detect again
    cached = list((tmp_path / "stereo.detections").glob("*.npz"))
    assert len(cached) == 2


def test_detection_cache_is_reused(stereo_folders, tmp_path, monkeypatch):
    board = ChessboardBoard(9, 6, 30.0)
    srcs = [stereo_folders["left"]]
    first = detect_cameras(srcs, board, cache_dir=tmp_path / "c", jobs=1, progress=False)
    import freipose.calibration.detect_videos as det

    def boom(*a, **k):
        raise AssertionError("re-detected despite the cache")

    monkeypatch.setattr(det, "_detect_chunk", boom)
    again = detect_cameras(srcs, board, cache_dir=tmp_path / "c", jobs=1, progress=False)
    assert np.array_equal(first[0].points, again[0].points, equal_nan=True)
    # another board is another cache entry
    with pytest.raises(AssertionError, match="re-detected"):
        detect_cameras(srcs, ChessboardBoard(9, 6, 25.0), cache_dir=tmp_path / "c", jobs=1)


def test_parallel_detection_matches_serial(stereo_folders):
    board = ChessboardBoard(9, 6, 30.0)
    srcs = [stereo_folders["left"], stereo_folders["right"]]
    a = detect_cameras(srcs, board, jobs=1, progress=False)
    b = detect_cameras(srcs, board, jobs=2, progress=False)
    for x, y in zip(a, b):
        assert np.array_equal(x.points, y.points, equal_nan=True)


def test_chessboard_orientation_is_physical(shared_data):
    # corners are numbered from the board's black corner square, however the image is rotated
    import cv2

    board = ChessboardBoard(9, 6, 30.0)
    img_dir = shared_data / "opencv-bouguet-stereo" / "images"
    for name in ("left01.jpg", "right05.jpg", "left12.jpg"):
        img = cv2.imread(str(img_dir / name))
        h, w = img.shape[:2]
        _ids, p = detect_image(img, board)
        _ids, q = detect_image(np.ascontiguousarray(img[::-1, ::-1]), board)
        back = np.stack([w - 1 - q[:, 0], h - 1 - q[:, 1]], axis=1)
        assert np.abs(back - p).max() < 0.2, name


def test_charuco_tutorial_detection_and_wrong_size(shared_data):
    import cv2

    img = cv2.imread(str(shared_data / "opencv-charuco-tutorial" / "choriginal.jpg"))
    board = CharucoBoard(5, 7, 40.0, 20.0, "DICT_6X6_250")
    ids, pts = detect_image(img, board)
    assert sorted(ids.tolist()) == list(range(24))
    K = np.array([[452.51, 0, 317.70], [0, 456.77, 277.75], [0, 0, 1]])
    dist = np.array([0.12137, -1.08547, 0.000118, -0.000462, 2.95426])
    ok, rvec, tvec = cv2.solvePnP(board.object_points[ids], pts, K, dist)
    proj, _ = cv2.projectPoints(board.object_points[ids], rvec, tvec, K, dist)
    rms = np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - pts) ** 2, axis=1)))
    assert rms < 0.3
    assert np.allclose(tvec.ravel(), [-91, -189, 399], atol=5)
    wrong = CharucoBoard(7, 5, 40.0, 20.0, "DICT_6X6_250")
    assert len(detect_image(img, wrong)[0]) == 0
    hint = diagnose_board([img], wrong)
    assert "squares_x = 5, squares_y = 7" in hint
    hint = diagnose_board([img], CharucoBoard(5, 7, 40.0, 20.0, "DICT_4X4_50"))
    assert "DICT_6X6" in hint
