"""The world frame of a calibrated rig: a camera's frame, or the board on the floor."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from freipose.calibration.bundle import BundleResult
from freipose.calibration.detect import CameraDetections
from freipose.calibration.intrinsics import CalibrationError
from freipose.calibration.params import DIST, FRAME_RVEC, FRAME_TVEC, RVEC, TVEC
from freipose.geometry import Camera
from freipose.geometry.transforms import invert_transform, rodrigues, transform
from freipose.io.calibration_world import WorldUp

__all__ = ["BOARD_TO_FLOOR", "WorldFrame", "rig_cameras", "world_frame"]

# board frame (x right, y down the print, z into the board) -> floor frame (z up out of it)
BOARD_TO_FLOOR = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class WorldFrame:
    """The adjusted rig and board poses in the world frame.

    Attributes:
        cameras: (C, 4, 4) world→camera of every camera (mm).
        board_poses: (F, 4, 4) board→world per frame, NaN where not estimated.
        description: the world frame in words (for the calibration file).
        up: the world's up direction, None when unknown.
    """

    cameras: np.ndarray
    board_poses: np.ndarray
    description: str
    up: WorldUp | None = None


def _origin_pose(board_poses: np.ndarray, origin_frame: int) -> np.ndarray:
    """(4, 4) board→bundle frame of ``origin_frame``.

    Raises:
        CalibrationError: the frame has no board pose (the message names frames near it
            that have one).
    """
    F = len(board_poses)
    N = int(origin_frame)
    if not (0 <= N < F) or not np.isfinite(board_poses[N, 0, 0]):
        seen = np.flatnonzero(np.isfinite(board_poses[:, 0, 0]))
        near = seen[np.argsort(np.abs(seen - N))[:5]]
        raise CalibrationError(
            f"--origin-frame {N}: the board pose in that frame is unknown (no camera "
            f"detected enough of the board; the videos have {F} frames). Frames with a board "
            f"pose near it: {', '.join(str(int(x)) for x in sorted(near))}"
        )
    return board_poses[N]


def world_frame(
    ba: BundleResult,
    num_frames: int,
    names: Sequence[str],
    origin_frame: int | None,
    up: Sequence[float] | None = None,
) -> WorldFrame:
    """Move the adjusted rig into the world frame.

    Args:
        ba: the bundle adjustment (cameras and board poses in its root camera's frame).
        num_frames: F, the frames of the videos.
        names: the camera names, in rig order.
        origin_frame: the frame whose board, laid on the floor, defines the world; ``None``:
            the first camera's frame.
        up: (3,) the up direction in the first camera's frame (without ``origin_frame``).

    Raises:
        CalibrationError: ``origin_frame`` and ``up`` both given, or an origin frame
            without a board pose.

    Returns:
        the cameras' and board poses' transforms in the world frame.
    """
    Tc = np.stack([transform(rodrigues(p[RVEC]), p[TVEC]) for p in ba.cam_params])  # world→cam
    Bw = np.full((num_frames, 4, 4), np.nan)
    for k, f in enumerate(ba.frames):
        Bw[f] = transform(rodrigues(ba.frame_params[k, FRAME_RVEC]), ba.frame_params[k, FRAME_TVEC])
    world_up = None
    if origin_frame is not None and up is not None:
        raise CalibrationError(
            "--origin-frame and --up both set the up direction (the board on the floor has z "
            "up): pass one"
        )
    if origin_frame is not None:
        N = int(origin_frame)
        W = BOARD_TO_FLOOR @ invert_transform(_origin_pose(Bw, N))
        world = (
            f"board on the floor in frame {N}: origin at the board's top-left pattern corner, "
            f"x along the board's rows, y toward its first row, z up out of the floor; mm"
        )
        world_up = WorldUp(np.array([0.0, 0.0, 1.0]), f"the board on the floor in frame {N}", 0.0)
    else:
        W = Tc[0].copy()
        world = (
            f"camera {names[0]}'s frame (origin at its optical centre, x right, y down, "
            f"z forward); mm"
        )
        if up is not None:
            world_up = WorldUp(np.asarray(up, dtype=np.float64), "given with --up")
    Tc = np.stack([T @ invert_transform(W) for T in Tc])
    Bw = np.einsum("ij,fjk->fik", W, Bw)
    return WorldFrame(Tc, Bw, world, world_up)


def rig_cameras(
    dets: Sequence[CameraDetections], ba: BundleResult, world_to_cam: np.ndarray
) -> tuple[Camera, ...]:
    """The calibrated cameras.

    Args:
        dets: per camera, the detections (names and image sizes).
        ba: the bundle adjustment (intrinsics and distortion).
        world_to_cam: (C, 4, 4) world→camera of every camera.

    Returns:
        one camera per detection, with its rotation made exactly orthonormal.
    """
    cams = []
    for i, d in enumerate(dets):
        p = ba.cam_params[i]
        K = np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1.0]])
        R = world_to_cam[i, :3, :3]
        U, _s, Vt = np.linalg.svd(R)
        cams.append(
            Camera(d.name, tuple(d.size), K, p[DIST].copy(), U @ Vt, world_to_cam[i, :3, 3])
        )
    return tuple(cams)
