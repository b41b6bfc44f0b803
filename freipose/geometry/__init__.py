"""Camera geometry for FreiPose: the conventions every module follows.

Conventions (stated once, here and in ``docs/formats.md``):

* **Units** are millimetres for every length in the world (camera translations, 3D
  points, board squares). Pixels are pixels.
* **Extrinsics** are world→camera: ``x_cam = R @ X + t``. The camera centre in the world
  is ``C = -R.T @ t``. Camera axes follow OpenCV: x right, y down, z forward (the
  optical axis).
* **Pixels**: the origin is the *centre* of the top-left pixel, so pixel centres sit
  at integer coordinates (OpenCV's convention). ``u`` is the column, ``v`` the row.
* **Intrinsics** ``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]``; the skew ``s`` is
  honoured everywhere (OpenCV's ``projectPoints``/``undistortPoints`` drop it).
* **Distortion** is OpenCV's five-parameter model ``(k1, k2, p1, p2, k3)`` applied to
  normalized coordinates before ``K``.
* **Array axes** are ``(time, camera, keypoint, xyz)``: 3D poses are ``(T, K, 3)``, 2D
  observations ``(T, C, K, 2)``, per-view confidences ``(T, C, K)``.
* **Missing values** are NaN. Functions skip NaN observations; they never treat them
  as zeros. A result that cannot be computed (fewer than two views, a point behind a
  camera) is NaN.

Modules: :mod:`.camera` (``Camera``, ``CameraRig``), :mod:`.transforms` (rotation
vectors, 4x4 transforms), :mod:`.distortion` (the lens distortion, its derivatives and
inverse), :mod:`.pinhole` (intrinsics and projection on arrays), :mod:`.projection`
(projection, undistortion and rays of cameras), :mod:`.triangulation` (DLT, weighted,
robust), :mod:`.torch_ops` (differentiable PyTorch versions for the network).
"""

from freipose.geometry.camera import Camera, CameraRig
from freipose.geometry.distortion import distort_normalized, undistort_normalized
from freipose.geometry.pinhole import apply_intrinsics, remove_intrinsics
from freipose.geometry.projection import pixel_to_ray, project, project_rig, undistort_pixels
from freipose.geometry.triangulation import (
    reprojection_errors,
    triangulate,
    triangulate_robust,
    triangulate_weighted,
)

__all__ = [
    "Camera",
    "CameraRig",
    "apply_intrinsics",
    "distort_normalized",
    "pixel_to_ray",
    "project",
    "project_rig",
    "remove_intrinsics",
    "reprojection_errors",
    "triangulate",
    "triangulate_robust",
    "triangulate_weighted",
    "undistort_normalized",
    "undistort_pixels",
]
