"""Boards seen from behind (transparent or double-sided prints): found in the mirror image."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from freipose.calibration.boards import AprilGridBoard, CharucoBoard, ChessboardBoard
from freipose.calibration.detect import CameraDetections, board_side, detect_image, mirror_x
from freipose.calibration.tracking import BoardTracker

BOARDS = [
    CharucoBoard(5, 4, 30.0, 22.0, "DICT_4X4_50"),
    AprilGridBoard(4, 3, 30.0, 0.3),
    dataclasses.replace(CharucoBoard(5, 4, 30.0, 22.0, "DICT_4X4_50"), inverted=True),
]


def _on_paper(tex: np.ndarray, pad: int = 40) -> np.ndarray:
    out = np.full((tex.shape[0] + 2 * pad, tex.shape[1] + 2 * pad), 255, np.uint8)
    out[pad:-pad, pad:-pad] = tex
    return out


def _sorted(ids: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    o = np.argsort(ids)
    return ids[o], pts[o]


def test_mirror_x_uses_the_pixel_centre_convention():
    np.testing.assert_array_equal(
        mirror_x(np.array([[0.0, 3.0], [9.0, 1.0]]), 10), [[9, 3], [0, 1]]
    )


@pytest.mark.parametrize("board", BOARDS, ids=["charuco", "aprilgrid", "charuco-inverted"])
def test_mirrored_print_gives_the_same_corners_flipped_back(board):
    import cv2

    img = _on_paper(board.texture(3.0))
    ids, pts = _sorted(*detect_image(img, board))
    assert len(ids) == len(board.object_points)
    back = cv2.flip(img, 1)  # a double-sided print's back, or a transparent print from behind
    ids_b, pts_b = _sorted(*detect_image(back, board))
    assert np.array_equal(ids_b, ids)  # the same physical corners ...
    # ... at the mirrored pixels: flipped back, they are where the front view has them
    np.testing.assert_allclose(mirror_x(pts_b, img.shape[1]), pts, atol=0.1)
    full = np.full((1, len(board.object_points), 2), np.nan)
    full[0, ids_b] = pts_b
    assert board_side(full, board.object_points)[0] == 1
    full[0, ids] = pts
    assert board_side(full, board.object_points)[0] == 0


@pytest.mark.parametrize("board", BOARDS[:2], ids=["charuco", "aprilgrid"])
def test_tracker_follows_a_board_seen_from_behind(board):
    import cv2

    img = _on_paper(board.texture(3.0))
    ids, pts = _sorted(*detect_image(img, board))
    back = cv2.flip(img, 1)
    track = BoardTracker(board)
    frames = [img, back, back, back, img, back]
    outs = [track.track(f) for f in frames]
    assert track.mirrored == 4
    for f, out in zip(frames, outs):
        want = pts if f is img else mirror_x(pts, img.shape[1])
        np.testing.assert_allclose(out[ids], want, atol=0.1)
    assert track.windowed >= 2  # mirrored frames after a mirrored one: tracked in windows
    sides = board_side(np.stack(outs), board.object_points)
    assert sides.tolist() == [0, 1, 1, 1, 0, 1]
    dets = CameraDetections("c", (img.shape[1], img.shape[0]), np.stack(outs), side=sides)
    assert dets.back_views == 4 and dets.truncated(2).back_views == 1


def test_normal_frames_without_a_board_are_not_searched_mirrored():
    board = BOARDS[0]
    track = BoardTracker(board)
    calls = []
    track._mirrored = lambda *a: calls.append(1)  # type: ignore[method-assign]
    blank = np.full((240, 320), 128, np.uint8)
    assert np.isnan(track.track(blank)).all()
    assert not calls


def _grid_mirror(pts_b: np.ndarray, pts: np.ndarray, nx: int, ny: int) -> None:
    """Assert that the mirrored points, flipped back, are the corners of a mirrored grid."""
    grid = pts.reshape(ny, nx, 2)
    cands = [grid[:, ::-1], grid[::-1, :]]
    assert any(np.abs(c.reshape(-1, 2) - pts_b).max() < 0.1 for c in cands)


def test_chessboard_from_behind_is_a_mirrored_grid():
    import cv2

    # a chessboard looks the same from behind as a mirrored front view: found directly, the
    # same corners, numbered as the mirrored grid (its back views cannot be told apart)
    board = ChessboardBoard(6, 5, 25.0)
    img = _on_paper(board.texture(3.0))
    ids, pts = detect_image(img, board)
    ids_b, pts_b = detect_image(cv2.flip(img, 1), board)
    assert np.array_equal(ids_b, ids)
    _grid_mirror(mirror_x(pts_b, img.shape[1]), pts, 6, 5)


def test_real_charuco_photo_mirrored(shared_data):
    import cv2

    img = cv2.imread(str(shared_data / "opencv-charuco-tutorial" / "choriginal.jpg"))
    board = CharucoBoard(5, 7, 40.0, 20.0, "DICT_6X6_250")
    ids, pts = _sorted(*detect_image(img, board))
    for variant, inverted in ((cv2.flip(img, 1), False), (255 - cv2.flip(img, 1), True)):
        b = dataclasses.replace(board, inverted=inverted)
        ids_m, pts_m = _sorted(*detect_image(variant, b))
        assert np.array_equal(ids_m, ids) and len(ids) == 24
        np.testing.assert_allclose(mirror_x(pts_m, img.shape[1]), pts, atol=0.1)
    track = BoardTracker(board)
    out = track.track(cv2.flip(img, 1))
    assert track.mirrored == 1
    np.testing.assert_allclose(mirror_x(out[ids], img.shape[1]), pts, atol=0.1)


def test_real_chessboard_photo_mirrored(shared_data):
    import cv2

    path = sorted((shared_data / "opencv-bouguet-stereo" / "images").glob("left*.jpg"))[0]
    img = cv2.imread(str(path))
    board = ChessboardBoard(9, 6, 30.0)
    ids, pts = detect_image(img, board)
    for variant, inverted in ((cv2.flip(img, 1), False), (255 - cv2.flip(img, 1), True)):
        b = dataclasses.replace(board, inverted=inverted)
        ids_m, pts_m = detect_image(variant, b)
        assert np.array_equal(ids_m, ids) and len(ids) == 54
        _grid_mirror(mirror_x(pts_m, img.shape[1]), pts, 9, 6)


def test_camera_below_a_transparent_floor_calibrates_like_the_others(tmp_path):
    from calib_helpers import rig_errors

    from freipose.calibration.detect_videos import detect_cameras
    from freipose.calibration.options import CalibrationOptions
    from freipose.calibration.pipeline import calibrate_detections
    from freipose.geometry import CameraRig
    from freipose.synth.board import default_board, write_board_videos
    from freipose.synth.rig import camera_below_floor, default_rig

    full = default_rig(3, size=(480, 360))
    rig = CameraRig((*full.cameras[:2], camera_below_floor("cam2", (480, 360))), full.metadata)
    board = default_board()
    vids, _poses = write_board_videos(
        tmp_path, rig, board, 80, seed=2, fmt=".mp4", workers=2, progress=False, transparent=True
    )
    dets = detect_cameras([vids[n] for n in rig.names], board, jobs=2, progress=False)
    below = dets[2]
    assert int((below.counts >= 4).sum()) >= 60
    assert below.back_views == int((below.counts >= 4).sum())  # it sees only the back
    res = calibrate_detections(dets, board, CalibrationOptions(jobs=2, progress=False))
    dc, rot, fe = rig_errors(res.rig, rig)
    assert dc.max() < 1.0 and rot.max() < 0.1 and np.abs(fe).max() < 0.3, (dc, rot, fe)
    from freipose.calibration.report import summary_dict

    sides = {n: c["back_side_views"] for n, c in summary_dict(res)["cameras"].items()}
    assert sides["cam2"] == below.back_views  # the report says which side each camera saw
