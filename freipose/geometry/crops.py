"""Square crops around a 3D point, and the cameras that see those crops.

A crop box is ``(x0, y0, x1, y1)`` in continuous pixel coordinates of the full image
(box edges, not pixel centres). Resizing it to ``out`` x ``out`` pixels maps an input
pixel ``u`` to ``(u + 0.5 - x0) / s - 0.5`` with ``s = (x1 - x0) / out``; the same affine
map applied to ``K`` (distortion unchanged, it acts before ``K``) gives the crop camera,
so projecting with the crop camera lands exactly on the cropped image.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from freipose.geometry.camera import Camera, CameraRig


def crop_affine(box: np.ndarray, out_size: int) -> np.ndarray:
    """The 3x3 affine map from full-image pixels to crop pixels for ``box`` (4,)."""
    x0, y0, x1, y1 = (float(v) for v in box)
    s = (x1 - x0) / out_size
    sy = (y1 - y0) / out_size
    if s <= 0 or sy <= 0:
        raise ValueError(f"crop box must have positive size, got {box}")
    return np.array(
        [[1 / s, 0.0, (0.5 - x0) / s - 0.5], [0.0, 1 / sy, (0.5 - y0) / sy - 0.5], [0.0, 0.0, 1.0]]
    )


def crop_camera(camera: Camera, box: np.ndarray, out_size: int) -> Camera:
    """The camera whose image is ``box`` of ``camera``'s image resized to ``out_size``."""
    A = crop_affine(box, out_size)
    return camera.replace(K=A @ camera.K, size=(out_size, out_size))


def warp_to_crop(
    image: np.ndarray, A: np.ndarray, out_size: int, border: int | tuple[int, ...] = 128
) -> np.ndarray:
    """Resample ``image`` (H, W[, C]) through the affine ``A`` (3, 3) into an ``out_size`` crop.

    Bilinear resampling alone aliases when the crop shrinks the image by more than 2x (fur
    texture turns into moire, a paw a few pixels wide flickers in and out): the part of the
    image the crop samples is first halved with a Gaussian pyramid (``cv2.pyrDown``) until
    the remaining shrink is at most 2x. A crop that shrinks less is a plain bilinear warp.
    Areas outside the image are filled with ``border``.

    Args:
        image: the full frame, uint8.
        A: (3, 3) affine map from full-image pixels to crop pixels (pixel centres at
            integers, as everywhere in FreiPose).
        out_size: side of the square crop.
        border: fill value (one per channel, or one for all).

    Returns:
        (out_size, out_size[, C]) the crop, same dtype as ``image``.
    """
    src, M = _pyramid_source(image, np.asarray(A, dtype=np.float64), out_size)
    channels = src.shape[2] if src.ndim == 3 else 1
    bv = tuple(border) if isinstance(border, tuple) else (border,) * channels
    return cv2.warpAffine(
        src,
        M[:2],
        (out_size, out_size),
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=bv,
    )


def _pyramid_source(
    image: np.ndarray, A: np.ndarray, out_size: int
) -> tuple[np.ndarray, np.ndarray]:
    """The region of ``image`` that the crop ``A`` samples, halved while ``A`` shrinks it > 2x.

    Returns:
        ``(source, M)``: the (possibly cut and halved) image and the affine from its pixels
        to the crop's. Pyramid pixel ``i`` is the Gaussian-weighted mean around pixel ``2i``
        of the level below, so each halving multiplies the affine by ``diag(2, 2, 1)``.
    """
    scale = math.sqrt(abs(float(np.linalg.det(A[:2, :2]))))
    if not scale < 0.5:
        return image, A
    h, w = image.shape[:2]
    e = out_size - 0.5
    corners = np.linalg.inv(A) @ np.array([[-0.5, e, -0.5, e], [-0.5, -0.5, e, e], [1, 1, 1, 1]])
    margin = 4.0 / scale  # the pyramid's 5-tap filters read beyond the sampled area
    x0 = max(int(math.floor(corners[0].min() - margin)) // 2 * 2, 0)
    y0 = max(int(math.floor(corners[1].min() - margin)) // 2 * 2, 0)
    x1 = min(int(math.ceil(corners[0].max() + margin)), w)
    y1 = min(int(math.ceil(corners[1].max() + margin)), h)
    if x1 - x0 < 2 or y1 - y0 < 2:
        return image, A  # the crop lies (almost) outside the image: border fill
    src = image[y0:y1, x0:x1]
    M = A @ np.array([[1.0, 0.0, x0], [0.0, 1.0, y0], [0.0, 0.0, 1.0]])
    while scale < 0.5 and min(src.shape[:2]) >= 2:
        src = cv2.pyrDown(src)
        M = M @ np.diag([2.0, 2.0, 1.0])
        scale *= 2.0
    return src, M


def crop_image(image: np.ndarray, box: np.ndarray, out_size: int, border: int = 128) -> np.ndarray:
    """Cut ``box`` out of ``image`` (H, W[, 3]) and resize to (out_size, out_size[, 3]).

    Areas outside the image are filled with ``border`` (grey); a box more than twice the
    crop's size is antialiased (:func:`warp_to_crop`).
    """
    return warp_to_crop(image, crop_affine(box, out_size), out_size, border)


def label_centers(points3d: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Mean of each instant's labeled 3D points: the centre a voxel cube is placed on.

    Args:
        points3d: (..., K, 3) 3D points (mm), NaN where unlabeled.
        mask: (..., K) points to use (also finite ones only) [default: every finite point].

    Returns:
        (..., 3) the mean of the used points; NaN where an instant has none.
    """
    p = np.asarray(points3d, dtype=np.float64)
    ok = np.asarray(np.isfinite(p).all(-1))
    if mask is not None:
        ok = ok & np.asarray(mask, dtype=bool)
    total = np.where(ok[..., None], p, 0.0).sum(-2)
    count = ok.sum(-1)[..., None]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan)


def cube_corners(center: np.ndarray, size: float) -> np.ndarray:
    """Corners (..., 8, 3) of axis-aligned cubes of edge ``size`` mm around centres (..., 3)."""
    c = np.asarray(center, dtype=np.float64)
    offs = (np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, 8).T) * (
        size / 2
    )
    return c[..., None, :] + offs


def cube_crop_boxes(rig: CameraRig, centers: np.ndarray, cube_size: float) -> np.ndarray:
    """Square boxes enclosing the projection of a cube around each centre, per camera.

    Args:
        rig: the cameras (C).
        centers: (..., 3) world mm (NaN gives NaN boxes).
        cube_size: cube edge in mm.

    Returns:
        (..., C, 4) boxes ``(x0, y0, x1, y1)``, square, centred on the projected centre.
    """
    c = np.asarray(centers, dtype=np.float64)
    points = np.concatenate([c[..., None, :], cube_corners(c, cube_size)], axis=-2)  # (..., 9, 3)
    uv = rig.project(points)  # (..., C, 9, 2)
    mid = uv[..., 0, :]  # (..., C, 2)
    half = np.max(np.abs(uv[..., 1:, :] - mid[..., None, :]), axis=(-2, -1))  # (..., C)
    half = np.where(np.isfinite(half), half, np.nan)
    return np.concatenate([mid - half[..., None], mid + half[..., None]], axis=-1)
