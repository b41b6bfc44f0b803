"""Inverted boards (white pattern on black): board files, printing, detection and diagnosis."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from calib_helpers import rendered_view

from freipose.calibration.board_files import board_from_dict, load_board, save_board
from freipose.calibration.boards import (
    AprilGridBoard,
    BoardError,
    CharucoBoard,
    ChessboardBoard,
    board_hash,
)
from freipose.calibration.detect import detect_image
from freipose.calibration.diagnose import diagnose_board
from freipose.calibration.tracking import BoardTracker

BOARDS = [
    CharucoBoard(5, 4, 30.0, 22.0, "DICT_4X4_50"),
    ChessboardBoard(6, 5, 25.0),
    AprilGridBoard(4, 3, 30.0, 0.3),
]


def _on_paper(tex: np.ndarray, pad: int = 40) -> np.ndarray:
    """The print on a larger white sheet (an inverted print keeps white paper around it)."""
    out = np.full((tex.shape[0] + 2 * pad, tex.shape[1] + 2 * pad), 255, np.uint8)
    out[pad:-pad, pad:-pad] = tex
    return out


@pytest.mark.parametrize("board", BOARDS, ids=lambda b: b.kind)
def test_inverted_key_round_trips_and_is_part_of_the_identity(board, tmp_path):
    inv = dataclasses.replace(board, inverted=True)
    assert "inverted" not in board.to_dict()  # normal boards: file and hash as before
    assert inv.to_dict()["inverted"] is True
    assert board_hash(inv) != board_hash(board)  # a cached normal detection is not reused
    save_board(inv, tmp_path / "b.toml")
    assert "inverted = true" in (tmp_path / "b.toml").read_text()
    assert load_board(tmp_path / "b.toml") == inv
    assert np.array_equal(inv.texture(1.0), 255 - board.texture(1.0))  # the printed negative
    with pytest.raises(BoardError, match="inverted must be true or false"):
        board_from_dict({**board.to_dict(), "inverted": "yes"})


@pytest.mark.parametrize("board", BOARDS, ids=lambda b: b.kind)
def test_inverted_print_is_detected_where_the_normal_one_is(board):
    inv = dataclasses.replace(board, inverted=True)
    normal_img = _on_paper(board.texture(3.0))
    inverted_img = _on_paper(inv.texture(3.0))
    ids, pts = detect_image(normal_img, board)
    assert len(ids) == len(board.object_points)
    assert len(detect_image(inverted_img, board)[0]) == 0  # refused without the key
    ids_i, pts_i = detect_image(inverted_img, inv)
    assert np.array_equal(np.sort(ids_i), np.sort(ids))
    np.testing.assert_allclose(pts_i[np.argsort(ids_i)], pts[np.argsort(ids)], atol=0.1)
    track = BoardTracker(inv)
    first, second = track.track(inverted_img), track.track(inverted_img)
    np.testing.assert_allclose(first[ids], pts, atol=0.1)
    np.testing.assert_allclose(second[ids], pts, atol=0.1)


@pytest.mark.parametrize("board", BOARDS[:1] + BOARDS[2:], ids=lambda b: b.kind)
def test_diagnosis_says_the_board_looks_inverted(board):
    inv = dataclasses.replace(board, inverted=True)
    hint = diagnose_board([_on_paper(inv.texture(3.0))], board, "board.toml")
    assert "the board looks inverted" in hint
    assert "add `inverted = true` to board.toml" in hint
    hint = diagnose_board([_on_paper(board.texture(3.0))], inv)
    assert "says inverted = true: remove that line" in hint


def test_chessboard_diagnosis_says_inverted():
    board = BOARDS[1]
    inv = dataclasses.replace(board, inverted=True)
    hint = diagnose_board([_on_paper(inv.texture(3.0))], board)
    assert "the board looks inverted" in hint and "the board file" in hint


def test_calib_board_prints_the_inverted_board(tmp_path):
    import cv2
    from click.testing import CliRunner

    from freipose.cli.main import cli

    board = dataclasses.replace(BOARDS[0], inverted=True)
    save_board(board, tmp_path / "b.toml")
    res = CliRunner().invoke(
        cli, ["calib", "board", str(tmp_path / "b.toml"), "-o", str(tmp_path / "b.png")]
    )
    assert res.exit_code == 0, res.output
    img = cv2.imread(str(tmp_path / "b.png"), cv2.IMREAD_GRAYSCALE)
    assert img[:10, :10].mean() > 200  # the top-left square, black on a normal print
    assert len(detect_image(_on_paper(img), board)[0]) == len(board.object_points)


def test_real_charuco_photo_inverted(shared_data):
    import cv2

    img = cv2.imread(str(shared_data / "opencv-charuco-tutorial" / "choriginal.jpg"))
    board = CharucoBoard(5, 7, 40.0, 20.0, "DICT_6X6_250")
    ids, pts = detect_image(img, board)
    neg = 255 - img
    assert len(detect_image(neg, board)[0]) == 0
    ids_i, pts_i = detect_image(neg, dataclasses.replace(board, inverted=True))
    assert np.array_equal(ids_i, ids) and len(ids) == 24
    np.testing.assert_allclose(pts_i, pts, atol=0.1)


def test_real_chessboard_photo_inverted(shared_data):
    import cv2

    path = sorted((shared_data / "opencv-bouguet-stereo" / "images").glob("left*.jpg"))[0]
    img = cv2.imread(str(path))
    board = ChessboardBoard(9, 6, 30.0)
    ids, pts = detect_image(img, board)
    assert len(ids) == 54
    ids_i, pts_i = detect_image(255 - img, dataclasses.replace(board, inverted=True))
    assert np.array_equal(ids_i, ids)
    np.testing.assert_allclose(pts_i, pts, atol=0.1)


def _tracked_errors(board, rig, poses, images) -> tuple[int, np.ndarray]:
    """Frames with a board found and the distances (px) of its corners from the truth."""
    from freipose.geometry import project

    track = BoardTracker(board)
    found, errs = 0, []
    for pose, img in zip(poses, images):
        p = track.track(img)
        m = np.isfinite(p[:, 0])
        if m.sum() >= 4:
            found += 1
            X = board.object_points[m] @ pose[:3, :3].T + pose[:3, 3]
            errs.append(np.linalg.norm(project(X, rig[0]) - p[m], axis=1))
    return found, np.concatenate(errs) if errs else np.zeros(0)


def test_rendered_inverted_board_corners_match_the_truth():
    from freipose.synth.board import render_board_frames

    rig, board, poses, normal = rendered_view(0, 60, 3, slice(0, 60, 2))
    inv = dataclasses.replace(board, inverted=True)
    images = render_board_frames(rig, inv, poses, seed=3)[rig[0].name]
    n_normal, e_normal = _tracked_errors(board, rig, poses, normal)
    n_inv, e_inv = _tracked_errors(inv, rig, poses, images)
    assert n_normal >= 10 and n_inv >= n_normal - 2
    assert np.median(e_inv) < 0.15 and np.median(e_inv) < 1.3 * np.median(e_normal)
