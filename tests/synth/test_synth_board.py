"""Calibration-board videos: poses, exact rendering with distortion, detectability."""

from __future__ import annotations

import numpy as np
import pytest

from freipose.calibration.board_files import load_board
from freipose.calibration.boards import CharucoBoard
from freipose.geometry import Camera, CameraRig, project
from freipose.synth import board_poses, default_board, render_board_frames, write_board_videos


def test_board_poses_are_rigid_and_start_on_the_floor():
    poses = board_poses(150, (600, 600), 1, (350, 280))
    R = poses[:, :3, :3]
    np.testing.assert_allclose(
        R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.det(R), 1.0)
    corners = np.array([[0, 0, 0, 1], [350, 0, 0, 1], [350, 280, 0, 1], [0, 280, 0, 1.0]])
    world = np.einsum("fij,pj->fpi", poses, corners)[..., :3]
    assert world[..., 2].min() > 0  # never below the floor
    np.testing.assert_allclose(world[0, :, 2], 0.5)  # first frame lies on the floor, centred
    np.testing.assert_allclose(world[0, :, :2].mean(0), 0, atol=1e-9)
    assert poses[0, 2, 2] == -1  # printed side (-z of the board) faces up
    assert np.linalg.norm(np.diff(world, axis=0), axis=-1).max() < 60  # smooth motion


def test_board_rendering_is_exact_with_distortion():
    board = CharucoBoard(5, 4, 60.0, 45.0, "DICT_4X4_50")
    cam = Camera.look_at("c", (0, -250, 700), (0, 0, 0), (640, 512), 660.0,
                         up=(0, 1, 0), dist=(-0.15, 0.03, 0.001, -0.001, 0))  # fmt: skip
    rig = CameraRig((cam,))
    poses = board_poses(1, (600, 600), 0, board.size_mm)
    img = (
        render_board_frames(rig, board, poses, seed=0, noise=False, px_per_mm=2.5)["c"][0]
        .astype(float)
        .mean(-1)
    )
    # mid-edge points 3.75 mm inside each square: black squares are dark there, white squares
    # (marker margin) bright — wherever the lens distortion puts them
    sx, sy = np.meshgrid(np.arange(5), np.arange(4))
    pts = np.stack([sx * 60.0 + 30.0, sy * 60.0 + 3.75, 0 * sx, 1 + 0 * sx], -1).reshape(-1, 4)
    uv = project((pts @ poses[0].T)[:, :3], cam)
    black = board.square_is_black(sx.ravel(), sy.ravel())
    vals = img[np.round(uv[:, 1]).astype(int), np.round(uv[:, 0]).astype(int)]
    assert vals[black].max() < 50 and vals[~black].min() > 120
    # a chessboard corner lies exactly between a dark and a bright square: its pixel is grey
    corner = project((np.array([60.0, 60.0, 0, 1]) @ poses[0].T)[:3], cam)
    u, v = corner
    assert 60 < np.mean(img[int(v) : int(v) + 2, int(u) : int(u) + 2]) < 180


def test_rendered_charuco_is_detected_at_the_true_corners():
    cv2 = pytest.importorskip("cv2")
    board = CharucoBoard(5, 4, 60.0, 45.0, "DICT_4X4_50")
    cam = Camera.look_at("c", (0, -250, 700), (0, 0, 0), (640, 512), 660.0, up=(0, 1, 0),
                         dist=(-0.1, 0.02, 0, 0, 0))  # fmt: skip
    poses = board_poses(1, (600, 600), 0, board.size_mm)
    img = render_board_frames(CameraRig((cam,)), board, poses, seed=0, px_per_mm=2.5)["c"][0]
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board.cv_board()).detectBoard(img)
    assert ids is not None and len(ids) == 12
    truth = project((np.c_[board.object_points, np.ones(12)] @ poses[0].T)[:, :3], cam)
    err = np.linalg.norm(corners.reshape(-1, 2) - truth[ids.ravel()], axis=1)
    assert np.median(err) < 0.15 and err.max() < 0.5


def test_write_board_videos(tmp_path):
    import cv2

    board = default_board()
    rig = CameraRig(tuple(
        Camera.look_at(f"c{i}", (600 * np.cos(a), 600 * np.sin(a), 700), (0, 0, 50), (96, 80), 90.0)
        for i, a in enumerate((0.3, 2.5))
    ))  # fmt: skip
    threads = cv2.getNumThreads()
    cv2.setNumThreads(3)
    try:
        videos, poses = write_board_videos(tmp_path, rig, board, 3, seed=2, fmt=".mkv")
        # rendered in this process with one OpenCV thread; the caller's setting is given back
        # (it once stayed at 1, which slowed down what ran next: aniposelib in the benchmark)
        assert cv2.getNumThreads() == 3
    finally:
        cv2.setNumThreads(threads)
    assert sorted(videos) == ["c0", "c1"] and poses.shape == (3, 4, 4)
    assert load_board(tmp_path / "board.toml") == board
    np.testing.assert_array_equal(np.load(tmp_path / "board_poses.npy"), poses)
    assert (tmp_path / "true_calibration.toml").is_file()
    assert all(p.is_file() for p in videos.values())


def test_write_board_videos_resumes(tmp_path):
    board = default_board()
    rig = CameraRig((Camera.look_at("c0", (600, 0, 700), (0, 0, 50), (64, 48), 60.0),))
    videos, _ = write_board_videos(tmp_path, rig, board, 2, seed=2, fmt=".mkv")
    before = videos["c0"].stat().st_mtime_ns
    write_board_videos(tmp_path, rig, board, 2, seed=2, fmt=".mkv")
    assert videos["c0"].stat().st_mtime_ns == before  # kept
    write_board_videos(tmp_path, rig, board, 2, seed=3, fmt=".mkv")
    assert videos["c0"].stat().st_mtime_ns != before  # another recording: rendered again
