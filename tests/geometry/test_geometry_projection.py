"""Projection, distortion, undistortion and rays: against OpenCV and hand formulas."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from freipose.geometry import (
    Camera,
    apply_intrinsics,
    distort_normalized,
    pixel_to_ray,
    project,
    project_rig,
    remove_intrinsics,
    undistort_normalized,
    undistort_pixels,
)

CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)


def _points(rng: np.random.Generator, n: int = 200) -> np.ndarray:
    """Points in a 300 mm box around the origin (all cameras of the circle rig see them)."""
    return rng.uniform(-150, 150, size=(n, 3))


def test_project_matches_opencv(distorted_rig, rng):
    X = _points(rng)
    for cam in distorted_rig:
        ours = project(X, cam)
        cv, _ = cv2.projectPoints(X, cam.rvec, cam.t, cam.K, cam.dist)
        np.testing.assert_allclose(ours, cv.reshape(-1, 2), atol=1e-6)
        # Without distortion: the pure pinhole model.
        cv0, _ = cv2.projectPoints(X, cam.rvec, cam.t, cam.K, np.zeros(5))
        np.testing.assert_allclose(project(X, cam, distort=False), cv0.reshape(-1, 2), atol=1e-6)


def test_undistort_matches_opencv(distorted_rig, rng):
    X = _points(rng)
    for cam in distorted_rig:
        uv = project(X, cam)
        cv = cv2.undistortPoints(uv.reshape(-1, 1, 2), cam.K, cam.dist, criteria=CRITERIA)
        ours = undistort_pixels(uv, cam)
        # Normalized coordinates times f ~ 800 px: compare in pixels.
        np.testing.assert_allclose(ours * 800, cv.reshape(-1, 2) * 800, atol=1e-6)
        ideal = undistort_pixels(uv, cam, to_pixels=True)
        np.testing.assert_allclose(ideal, project(X, cam, distort=False), atol=1e-6)


def test_distortion_round_trip_is_exact(rng):
    xy = rng.uniform(-0.4, 0.4, size=(500, 2))
    d = np.array([-0.25, 0.08, 0.002, -0.001, -0.01])
    back = undistort_normalized(distort_normalized(xy, d), d)
    np.testing.assert_allclose(back, xy, atol=1e-12)


def test_skew_is_honoured_and_opencv_drops_it(rng):
    skew = -5.8
    K = np.array([[1600.0, skew, 600.0], [0.0, 1610.0, 500.0], [0.0, 0.0, 1.0]])
    dist = np.array([-0.15, 0.9, -0.001, -0.004, -2.7])
    cam = Camera.look_at("c", (300, -200, 250), (0, 0, 0), (1200, 1000), 1600.0)
    cam = cam.replace(K=K, dist=dist)
    X = rng.uniform(-40, 40, size=(100, 3))
    # Hand formula: normalise, distort, then [u, v] = [fx x + s y + cx, fy y + cy].
    Xc = X @ cam.R.T + cam.t
    x, y = Xc[:, 0] / Xc[:, 2], Xc[:, 1] / Xc[:, 2]
    k1, k2, p1, p2, k3 = dist
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    hand = np.stack([K[0, 0] * xd + skew * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], -1)
    np.testing.assert_allclose(project(X, cam), hand, atol=1e-9)
    # OpenCV ignores K[0, 1]: its answer is off by skew * yd pixels.
    cv, _ = cv2.projectPoints(X, cam.rvec, cam.t, K, dist)
    cv_err = np.abs(cv.reshape(-1, 2)[:, 0] - hand[:, 0])
    np.testing.assert_allclose(cv_err, np.abs(skew * yd), atol=1e-6)
    assert cv_err.max() > 0.1
    # Undistortion honours the skew too: exact inverse of the projection.
    np.testing.assert_allclose(undistort_pixels(hand, cam), np.stack([x, y], -1), atol=1e-12)
    np.testing.assert_allclose(
        remove_intrinsics(apply_intrinsics(np.stack([xd, yd], -1), K), K),
        np.stack([xd, yd], -1),
        atol=1e-12,
    )


def test_behind_camera_and_nan_give_nan(circle_rig):
    cam = circle_rig[0]
    behind = cam.center + 2 * (cam.center - np.zeros(3))  # further out, behind the camera
    X = np.array([[0.0, 0.0, 0.0], behind, [np.nan, 0.0, 0.0]])
    uv = project(X, cam)
    assert np.isfinite(uv[0]).all()
    assert np.isnan(uv[1]).all() and np.isnan(uv[2]).all()


def test_origin_projects_to_principal_point(circle_rig):
    for cam in circle_rig:
        np.testing.assert_allclose(project(np.zeros(3), cam), cam.K[:2, 2], atol=1e-9)


def test_project_rig_shapes_and_errors(circle_rig, rng):
    X = rng.normal(size=(4, 5, 3))
    assert project_rig(X, circle_rig).shape == (4, 6, 5, 2)
    assert circle_rig.project(X).shape == (4, 6, 5, 2)
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 3\)"):
        project(np.zeros((5, 2)), circle_rig[0])
    with pytest.raises(ValueError, match=r"\(\.\.\., P, 3\)"):
        project_rig(np.zeros(3), circle_rig)
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 2\)"):
        undistort_pixels(np.zeros((3, 3)), circle_rig[0])


def test_pixel_to_ray_round_trip(distorted_rig, rng):
    X = _points(rng, 50)
    for cam in distorted_rig:
        origin, d = pixel_to_ray(project(X, cam), cam)
        np.testing.assert_allclose(origin, cam.center)
        np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
        # The world point lies on the ray: X = origin + s d with s = depth along the ray.
        v = X - origin
        s = np.sum(v * d, axis=-1)
        assert np.all(s > 0)
        np.testing.assert_allclose(origin + s[:, None] * d, X, atol=1e-6)
