"""Detectors that know only the board's markers detect exactly what full-dictionary ones do.

OpenCV compares every marker candidate with the dictionary's entries in id order and takes the
first within its error correction, so a dictionary cut to the board's ids 0..n-1 must give the
same board markers (and corners) and drop only the markers of other boards.
"""

from __future__ import annotations

import numpy as np
import pytest
from calib_helpers import rendered_view

cv2 = pytest.importorskip("cv2")


def test_board_dictionary_is_the_named_one_cut_to_the_board():
    from freipose.calibration.boards import board_dictionary, get_dictionary

    full = get_dictionary("DICT_5X5_100")
    cut = board_dictionary("DICT_5X5_100", 12)
    assert cut.bytesList.shape[0] == 12
    np.testing.assert_array_equal(cut.bytesList, full.bytesList[:12])
    assert (cut.markerSize, cut.maxCorrectionBits) == (full.markerSize, full.maxCorrectionBits)
    assert board_dictionary("DICT_4X4_50", 500).bytesList.shape[0] == 50


def _paste(image: np.ndarray, patch: np.ndarray, x: int, y: int) -> np.ndarray:
    out = image.copy()
    h, w = patch.shape[:2]
    out[y : y + h, x : x + w] = patch if out.ndim == 2 else patch[..., None]
    return out


def test_charuco_detector_with_board_markers_only_matches_full_dictionary():
    from freipose.calibration.detect import charuco_detector as _charuco_detector

    _rig, board, _poses, images = rendered_view(1, 40, 5, slice(4, None, 3))
    # a marker of another board (same dictionary, id beyond this board's) in every frame
    foreign_id = board.n_markers + 7
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    tag = cv2.aruco.generateImageMarker(dictionary, foreign_id, 36)
    tag = np.pad(tag, 20, constant_values=255)

    ours = _charuco_detector(board)
    cp = cv2.aruco.CharucoParameters()
    cp.minMarkers = ours.getCharucoParameters().minMarkers
    reference = cv2.aruco.CharucoDetector(board.cv_board(), cp, ours.getDetectorParameters())
    corners = 0
    for image in images:
        gray = _paste(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), tag, 4, 4)
        cc, ci, _mc, mi = ours.detectBoard(gray)
        rc, ri, _rmc, rmi = reference.detectBoard(gray)
        assert foreign_id in np.asarray(rmi).reshape(-1)  # the full dictionary sees it
        assert foreign_id not in np.asarray(mi).reshape(-1)
        board_ids = np.asarray(rmi).reshape(-1)
        np.testing.assert_array_equal(
            np.sort(np.asarray(mi).reshape(-1)), np.sort(board_ids[board_ids < board.n_markers])
        )
        if ri is None:
            assert ci is None or len(ci) == 0
            continue
        np.testing.assert_array_equal(np.asarray(ci), np.asarray(ri))
        np.testing.assert_array_equal(np.asarray(cc), np.asarray(rc))
        corners += len(ri)
    assert corners > 40  # the board is seen


def test_aprilgrid_detector_with_board_tags_only_matches_full_dictionary():
    from freipose.calibration.boards import AprilGridBoard, get_dictionary
    from freipose.calibration.detect import aruco_detector as _aruco_detector

    board = AprilGridBoard(tags_x=3, tags_y=2, tag_size=30.0, tag_spacing=0.3)
    tex = board.texture(3.0)
    h, w = tex.shape
    image = np.full((h + 120, w + 260), 255, np.uint8)
    image = _paste(image, tex, 60, 60)
    other = cv2.aruco.generateImageMarker(get_dictionary(board.dictionary), 40, 80, borderBits=2)
    image = _paste(image, other, w + 130, h // 2)  # a tag of another board, beside this one
    centre = (image.shape[1] / 2, image.shape[0] / 2)
    image = cv2.warpAffine(
        image, cv2.getRotationMatrix2D(centre, 8, 1.0), image.shape[::-1], borderValue=255
    )
    image = cv2.GaussianBlur(image, (3, 3), 0.8)

    ours = _aruco_detector(board.dictionary, board.border, board.n_tags)
    full = _aruco_detector(board.dictionary, board.border)
    c_ours, i_ours, _ = ours.detectMarkers(image)
    c_full, i_full, _ = full.detectMarkers(image)
    i_full = np.asarray(i_full).reshape(-1)
    assert 40 in i_full and set(range(board.n_tags)) <= set(i_full.tolist())
    i_ours = np.asarray(i_ours).reshape(-1)
    assert sorted(i_ours.tolist()) == list(range(board.n_tags))
    by_id = {int(i): np.asarray(c) for i, c in zip(i_full, c_full)}
    for i, c in zip(i_ours, c_ours):
        np.testing.assert_array_equal(np.asarray(c), by_id[int(i)])
