"""The bundle adjustment's parameter layout: named columns of a camera's and a board pose's row.

A camera is a row of 15 numbers ``fx fy cx cy k1 k2 p1 p2 k3 r1 r2 r3 t1 t2 t3``: focal
lengths and principal point (px), the OpenCV distortion ``(k1, k2, p1, p2, k3)``, and the
world→camera rotation vector and translation (mm). A board pose is a row of 6 numbers
``r1 r2 r3 t1 t2 t3``: the board→world rotation vector and translation (mm). Index the rows
(or the last axis of a (C, 15) / (F, 6) array) with the slices below instead of literal
column numbers.
"""

from __future__ import annotations

import numpy as np

from freipose.calibration.intrinsics import CalibrationError
from freipose.geometry.camera import Camera
from freipose.geometry.transforms import matrix_to_rodrigues

__all__ = [
    "CAM_PARAMS",
    "DIST",
    "EXTRINSICS",
    "FOCAL",
    "FRAME_PARAMS",
    "FRAME_RVEC",
    "FRAME_TVEC",
    "INTRINSICS",
    "PINHOLE",
    "PRINCIPAL",
    "RVEC",
    "TANGENTIAL",
    "TVEC",
    "camera_to_params",
    "params_to_camera",
]

CAM_PARAMS = 15  # columns of a camera row
FOCAL = slice(0, 2)  # fx fy
PRINCIPAL = slice(2, 4)  # cx cy
PINHOLE = slice(0, 4)  # fx fy cx cy
DIST = slice(4, 9)  # k1 k2 p1 p2 k3
TANGENTIAL = slice(6, 8)  # p1 p2
INTRINSICS = slice(0, 9)  # focal, principal point and distortion
RVEC = slice(9, 12)  # world→camera rotation vector
TVEC = slice(12, 15)  # world→camera translation (mm)
EXTRINSICS = slice(9, 15)  # rotation vector and translation

FRAME_PARAMS = 6  # columns of a board-pose row
FRAME_RVEC = slice(0, 3)  # board→world rotation vector
FRAME_TVEC = slice(3, 6)  # board→world translation (mm)


def camera_to_params(cam: Camera) -> np.ndarray:
    """A camera's row of bundle-adjustment parameters.

    Args:
        cam: a camera without skew (``K[0, 1] == 0``).

    Returns:
        (15,) ``fx fy cx cy k1 k2 p1 p2 k3 r1 r2 r3 t1 t2 t3``.

    Raises:
        CalibrationError: the camera's intrinsic matrix has a skew term, which the bundle
            adjustment does not model.
    """
    K = cam.K
    if K[0, 1] != 0:
        raise CalibrationError(
            f"camera {cam.name}: the bundle adjustment models no skew, but K[0, 1] is {K[0, 1]}"
        )
    p = np.zeros(CAM_PARAMS)
    p[FOCAL] = (K[0, 0], K[1, 1])
    p[PRINCIPAL] = (K[0, 2], K[1, 2])
    p[DIST] = cam.dist
    p[RVEC] = matrix_to_rodrigues(cam.R)
    p[TVEC] = cam.t
    return p


def params_to_camera(name: str, size: tuple[int, int], p: np.ndarray) -> Camera:
    """The camera of a row of bundle-adjustment parameters.

    Args:
        name: the camera's name.
        size: its image size ``(width, height)`` in pixels.
        p: (15,) ``fx fy cx cy k1 k2 p1 p2 k3 r1 r2 r3 t1 t2 t3``.

    Returns:
        The camera (no skew; the rotation from the rotation vector by OpenCV).
    """
    p = np.asarray(p, dtype=np.float64)
    (fx, fy), (cx, cy) = p[FOCAL], p[PRINCIPAL]
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return Camera.from_rvec(name, size, K, p[DIST].copy(), p[RVEC], p[TVEC].copy())
