"""Camera / CameraRig validation and derived quantities; crop cameras and cube boxes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from freipose.geometry import Camera, CameraRig, project
from freipose.geometry.crops import (
    crop_affine,
    crop_camera,
    crop_image,
    cube_corners,
    cube_crop_boxes,
    warp_to_crop,
)
from freipose.geometry.transforms import matrix_to_rodrigues, rodrigues_to_matrix

K0 = [[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]]


def test_camera_validation_messages():
    with pytest.raises(ValueError, match="non-empty string"):
        Camera("", (640, 480), K0)
    with pytest.raises(ValueError, match="size must be positive"):
        Camera("c", (0, 480), K0)
    with pytest.raises(ValueError, match=r"size must be \(width, height\)"):
        Camera("c", "big", K0)
    with pytest.raises(ValueError, match=r"K must have shape \(3, 3\)"):
        Camera("c", (640, 480), np.eye(4))
    with pytest.raises(ValueError, match="fx, fy > 0"):
        Camera("c", (640, 480), [[-800, 0, 320], [0, 800, 240], [0, 0, 1]])
    with pytest.raises(ValueError, match="NaN or infinite"):
        Camera("c", (640, 480), K0, t=[0, np.nan, 0])
    with pytest.raises(ValueError, match="not a rotation"):
        Camera("c", (640, 480), K0, R=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="5-parameter"):
        Camera("c", (640, 480), K0, dist=[0.1, 0, 0, 0, 0, 0.3, 0, 0])
    # Four coefficients are padded, eight with zero extras are accepted.
    assert Camera("c", (640, 480), K0, dist=[0.1, 0.2, 0, 0]).dist.tolist() == [0.1, 0.2, 0, 0, 0]
    assert Camera("c", (640, 480), K0, dist=[0.1, 0, 0, 0, 0, 0, 0, 0]).dist.shape == (5,)


def test_camera_is_frozen_and_derived_values():
    cam = Camera.look_at("c", (1000, 0, 500), (0, 0, 0), (640, 480), 800.0)
    with pytest.raises(AttributeError):
        cam.name = "x"  # type: ignore[misc]
    with pytest.raises(ValueError):
        cam.K[0, 0] = 1.0  # read-only array
    np.testing.assert_allclose(cam.center, (1000, 0, 500), atol=1e-9)
    np.testing.assert_allclose(cam.R @ cam.R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(cam.extrinsics[:3, 3], cam.t)
    np.testing.assert_allclose(cam.P, cam.K @ np.hstack([cam.R, cam.t[:, None]]))
    # The world up vector points up in the image (negative v direction).
    top = project(np.array([0.0, 0.0, 50.0]), cam)
    assert top[1] < project(np.zeros(3), cam)[1]
    again = Camera.from_rvec("c", (640, 480), cam.K, cam.dist, cam.rvec, cam.t)
    assert again.allclose(cam)
    np.testing.assert_allclose(rodrigues_to_matrix(matrix_to_rodrigues(cam.R)), cam.R, atol=1e-12)
    assert cam.replace(name="d").name == "d" and not cam.replace(name="d").allclose(cam)
    assert (cam.width, cam.height) == (640, 480) and not cam.has_distortion
    assert "center=(1000.0, 0.0, 500.0)" in repr(cam)
    with pytest.raises(ValueError, match="coincide"):
        Camera.look_at("c", (0, 0, 0), (0, 0, 0), (640, 480), 800.0)


def test_rig_lookup_and_validation(circle_rig):
    assert circle_rig.names == [f"cam{i}" for i in range(6)]
    assert circle_rig["cam2"] is circle_rig[2] and circle_rig.index("cam4") == 4
    assert "cam5" in circle_rig and "cam9" not in circle_rig
    with pytest.raises(KeyError, match="no camera named 'cam9'"):
        circle_rig["cam9"]
    with pytest.raises(KeyError, match="cameras are"):
        circle_rig.index("nope")
    sub = circle_rig.subset(["cam3", "cam1"])
    assert sub.names == ["cam3", "cam1"] and sub.metadata == circle_rig.metadata
    assert circle_rig.K.shape == (6, 3, 3) and circle_rig.dist.shape == (6, 5)
    assert circle_rig.R.shape == (6, 3, 3) and circle_rig.t.shape == (6, 3)
    assert circle_rig.sizes.tolist() == [[640, 480]] * 6
    np.testing.assert_allclose(np.linalg.norm(circle_rig.centers[:, :2], axis=1), 1000.0)
    with pytest.raises(ValueError, match="repeated"):
        CameraRig((circle_rig[0], circle_rig[0]))
    with pytest.raises(ValueError, match="at least one camera"):
        CameraRig(())
    with pytest.raises(ValueError, match="Camera objects"):
        CameraRig(("cam0",))  # type: ignore[arg-type]
    with pytest.raises(TypeError):
        circle_rig.metadata["x"] = 1  # type: ignore[index]
    assert circle_rig.with_metadata(origin="floor").metadata["origin"] == "floor"
    assert circle_rig.allclose(circle_rig.subset(circle_rig.names))


def test_crop_camera_matches_affine_mapped_projection(distorted_rig, rng):
    X = rng.uniform(-100, 100, size=(50, 3))
    for cam in distorted_rig:
        box = np.array([100.3, 50.7, 420.3, 370.7])
        ccam = crop_camera(cam, box, 224)
        A = crop_affine(box, 224)
        uv = project(X, cam)
        mapped = uv @ A[:2, :2].T + A[:2, 2]
        np.testing.assert_allclose(project(X, ccam), mapped, atol=1e-9)
        assert ccam.size == (224, 224)
    with pytest.raises(ValueError, match="positive size"):
        crop_affine([10, 10, 5, 20], 64)


def test_crop_image_samples_the_box():
    img = np.zeros((100, 200), dtype=np.uint8)
    img[40:60, 80:120] = 255
    crop = crop_image(img, np.array([80.0, 40.0, 120.0, 60.0]), 20)  # 2x downsampling in x
    assert crop.shape == (20, 20)
    assert crop[5:15, 5:15].min() == 255
    out = crop_image(np.zeros((10, 10, 3), np.uint8), np.array([-50.0, -50.0, -10.0, -10.0]), 8)
    assert out.shape == (8, 8, 3) and (out == 128).all()


def test_crop_shrinking_less_than_2x_is_the_plain_bilinear_warp(rng):
    img = rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)
    A = crop_affine(np.array([20.5, 10.0, 110.5, 100.0]), 64)  # shrinks 1.4x
    plain = cv2.warpAffine(img, A[:2], (64, 64), flags=cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=(128, 128, 128))  # fmt: skip
    np.testing.assert_array_equal(warp_to_crop(img, A, 64), plain)


def test_crop_shrinking_more_than_2x_is_antialiased():
    # a one-pixel checkerboard averages to grey; bilinear sampling at a 4x shrink picks
    # single pixels and keeps full contrast (aliasing)
    yy, xx = np.mgrid[:512, :640]
    img = np.where((xx + yy) % 2 == 0, 255, 0).astype(np.uint8)
    box = np.array([64.0, 64.0, 576.0, 448.0 + 128.0])  # 512 px -> 128 px
    crop = crop_image(img, box, 128).astype(float)
    assert abs(crop.mean() - 127.5) < 3 and crop.std() < 10
    A = crop_affine(box, 128)
    aliased = cv2.warpAffine(img, A[:2], (128, 128), flags=cv2.INTER_LINEAR)
    assert aliased.std() > 30


@pytest.mark.parametrize("angle", [0.0, 30.0])
def test_antialiased_crop_keeps_points_where_the_affine_maps_them(angle):
    # a bright blob at a known image point lands where the crop affine puts it, also when
    # the crop is rotated and shrinks the image 5x (two pyramid halvings, then the warp)
    img = np.zeros((1024, 1280), np.uint8)
    u = np.array([701.0, 433.0])
    cv2.circle(img, (int(u[0]), int(u[1])), 9, 255, -1)
    c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    T = np.array([[1.0, 0.0, 64.0], [0.0, 1.0, 64.0], [0.0, 0.0, 1.0]])
    A = T @ R @ np.diag([0.2, 0.2, 1.0]) @ np.array([[1.0, 0, -640.0], [0, 1.0, -512.0], [0, 0, 1]])
    crop = warp_to_crop(img, A, 128, 0).astype(float)
    ys, xs = np.mgrid[:128, :128]
    got = np.array([(crop * xs).sum(), (crop * ys).sum()]) / crop.sum()
    want = (A @ [u[0], u[1], 1.0])[:2]
    np.testing.assert_allclose(got, want, atol=0.1)


def test_cube_boxes_contain_the_cube(circle_rig, rng):
    centers = rng.uniform(-100, 100, size=(7, 3))
    boxes = cube_crop_boxes(circle_rig, centers, 200.0)
    assert boxes.shape == (7, 6, 4)
    assert np.allclose(boxes[..., 2] - boxes[..., 0], boxes[..., 3] - boxes[..., 1])  # square
    inside = centers[:, None] + rng.uniform(-100, 100, size=(7, 500, 3))
    for ci, cam in enumerate(circle_rig):
        uv = project(inside, cam)  # (7, 500, 2)
        b = boxes[:, ci]
        assert np.all(uv[..., 0] >= b[:, None, 0] - 1e-9) and np.all(
            uv[..., 0] <= b[:, None, 2] + 1e-9
        )
        assert np.all(uv[..., 1] >= b[:, None, 1] - 1e-9) and np.all(
            uv[..., 1] <= b[:, None, 3] + 1e-9
        )
    assert cube_corners(np.zeros(3), 2.0).shape == (8, 3)
    assert np.isnan(cube_crop_boxes(circle_rig, np.full(3, np.nan), 100.0)).all()
