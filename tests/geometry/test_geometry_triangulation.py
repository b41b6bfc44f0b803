"""Triangulation: exact round trips, NaN handling, weights, RANSAC, shape errors."""

from __future__ import annotations

import numpy as np
import pytest

from freipose.geometry import (
    CameraRig,
    project_rig,
    reprojection_errors,
    triangulate,
    triangulate_robust,
    triangulate_weighted,
)


def _obs(rig: CameraRig, X: np.ndarray) -> np.ndarray:
    """(N, C, 2) observations of points X (N, 3)."""
    return np.moveaxis(project_rig(X, rig), -3, -2)


def test_round_trip_exact(distorted_rig, rng):
    X = rng.uniform(-200, 200, size=(300, 3))
    uv = _obs(distorted_rig, X)
    assert uv.shape == (300, 6, 2)
    np.testing.assert_allclose(triangulate(uv, distorted_rig), X, atol=1e-6)
    np.testing.assert_allclose(
        triangulate_weighted(uv, rng.uniform(0.1, 1, (300, 6)), distorted_rig, refine=True),
        X,
        atol=1e-6,
    )
    Xr, inl = triangulate_robust(uv, distorted_rig, threshold=1.0)
    np.testing.assert_allclose(Xr, X, atol=1e-6)
    assert inl.all()
    np.testing.assert_allclose(reprojection_errors(X, uv, distorted_rig), 0, atol=1e-6)


def test_leading_axes_are_kept(circle_rig, rng):
    X = rng.uniform(-100, 100, size=(2, 3, 4, 3))
    uv = np.moveaxis(project_rig(X, circle_rig), -3, -2)  # (2, 3, 4, C, 2)
    assert triangulate(uv, circle_rig).shape == (2, 3, 4, 3)
    np.testing.assert_allclose(triangulate(uv, circle_rig), X, atol=1e-6)


def test_missing_views_are_skipped_not_zeroed(distorted_rig, rng):
    X = rng.uniform(-100, 100, size=(20, 3))
    uv = _obs(distorted_rig, X)
    uv[:, [0, 2, 3]] = np.nan  # three of six views missing
    np.testing.assert_allclose(triangulate(uv, distorted_rig), X, atol=1e-6)
    uv[5, [1, 4]] = np.nan  # now point 5 is seen by one view only
    uv[6] = np.nan  # point 6 by none
    out = triangulate(uv, distorted_rig)
    assert np.isnan(out[5]).all() and np.isnan(out[6]).all()
    np.testing.assert_allclose(np.delete(out, [5, 6], 0), np.delete(X, [5, 6], 0), atol=1e-6)
    # Zero or NaN weight skips a view just like a missing observation.
    uv2 = _obs(distorted_rig, X)
    w = np.ones((20, 6))
    w[:, :5] = 0
    assert np.isnan(triangulate_weighted(uv2, w, distorted_rig)).all()
    w[:, 0] = np.nan
    w[:, 1] = 1
    np.testing.assert_allclose(triangulate_weighted(uv2, w, distorted_rig), X, atol=1e-6)
    err = reprojection_errors(X, uv, distorted_rig)
    assert np.isnan(err[:, 0]).all() and np.isnan(err[5, 1]) and np.isfinite(err[7, 1])


def test_weights_downweight_a_bad_view(circle_rig, rng):
    X = rng.uniform(-100, 100, size=(30, 3))
    uv = _obs(circle_rig, X)
    uv[:, 0] += 15.0  # a biased view
    w = np.ones((30, 6))
    plain = np.linalg.norm(triangulate_weighted(uv, w, circle_rig) - X, axis=-1)
    w[:, 0] = 0.01
    weighted = np.linalg.norm(triangulate_weighted(uv, w, circle_rig, refine=True) - X, axis=-1)
    assert weighted.mean() < 0.1 * plain.mean()


def test_ransac_rejects_a_view_off_by_200px(distorted_rig, rng):
    rig = distorted_rig.subset(["cam0", "cam1", "cam2", "cam4"])
    X = rng.uniform(-100, 100, size=(40, 3))
    uv = _obs(rig, X) + rng.normal(0, 0.3, size=(40, 4, 2))
    bad = rng.integers(0, 4, size=40)
    angle = rng.uniform(0, 2 * np.pi, size=40)
    uv[np.arange(40), bad] += 200 * np.stack([np.cos(angle), np.sin(angle)], -1)
    Xr, inl = triangulate_robust(uv, rig, threshold=10.0)
    expect = np.ones((40, 4), dtype=bool)
    expect[np.arange(40), bad] = False
    np.testing.assert_array_equal(inl, expect)
    assert np.linalg.norm(Xr - X, axis=-1).max() < 2.0  # mm, with 0.3 px noise
    plain = np.linalg.norm(triangulate(uv, rig) - X, axis=-1)
    assert plain.min() > 5.0  # the plain DLT is pulled away by the bad view


def test_ransac_min_inliers_and_no_consensus(circle_rig, rng):
    X = rng.uniform(-50, 50, size=(5, 3))
    uv = _obs(circle_rig, X)
    uv[:, 2:] = np.nan  # only two views
    Xr, inl = triangulate_robust(uv, circle_rig, min_inliers=3)
    assert np.isnan(Xr).all() and not inl.any()
    Xr, inl = triangulate_robust(uv, circle_rig, min_inliers=2)
    np.testing.assert_allclose(Xr, X, atol=1e-6)
    with pytest.raises(ValueError, match="min_inliers"):
        triangulate_robust(uv, circle_rig, min_inliers=1)


def test_shape_errors_are_clear(circle_rig):
    with pytest.raises(ValueError, match=r"\(\.\.\., C=6, 2\)"):
        triangulate(np.zeros((10, 5, 2)), circle_rig)
    with pytest.raises(ValueError, match="weights must have shape"):
        triangulate_weighted(np.zeros((10, 6, 2)), np.ones((10, 5)), circle_rig)
    with pytest.raises(ValueError, match="non-negative"):
        triangulate_weighted(np.zeros((1, 6, 2)), -np.ones((1, 6)), circle_rig)
    with pytest.raises(ValueError, match="points3d must have shape"):
        reprojection_errors(np.zeros((4, 3)), np.zeros((5, 6, 2)), circle_rig)
    with pytest.raises(ValueError, match="weights must have shape"):
        triangulate_robust(np.zeros((10, 6, 2)), circle_rig, weights=np.ones((10, 4)))
