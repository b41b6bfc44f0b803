"""Rotation vectors, 4x4 transforms and the distortion polynomial's derivatives."""

from __future__ import annotations

import numpy as np

from freipose.geometry.distortion import distortion_jacobian, distortion_terms
from freipose.geometry.transforms import (
    invert_transform,
    matrix_to_rodrigues,
    rodrigues,
    rodrigues_to_matrix,
    transform,
)


def test_vectorized_rodrigues_matches_opencv():
    rng = np.random.default_rng(0)
    r = rng.normal(0, 1, (20, 3))
    R = rodrigues(r)
    for k in range(len(r)):
        np.testing.assert_allclose(R[k], rodrigues_to_matrix(r[k]), atol=1e-12)
        np.testing.assert_allclose(rodrigues_to_matrix(matrix_to_rodrigues(R[k])), R[k], atol=1e-12)
    np.testing.assert_allclose(rodrigues(np.full(3, 1e-14)), np.eye(3), atol=1e-13)


def test_transform_and_inverse():
    R = rodrigues_to_matrix([0.3, -0.2, 1.1])
    t = np.array([10.0, -5.0, 300.0])
    T = transform(R, t.reshape(3, 1))
    np.testing.assert_array_equal(T[:3, :3], R)
    np.testing.assert_array_equal(T[:3, 3], t)
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    np.testing.assert_allclose(invert_transform(T) @ T, np.eye(4), atol=1e-12)


def test_distortion_jacobian_matches_finite_differences():
    rng = np.random.default_rng(1)
    x, y = rng.uniform(-0.5, 0.5, (2, 50))
    dist = rng.normal(0, 0.05, 5)
    J = distortion_jacobian(x, y, dist, distortion_terms(x, y, dist))
    h = 1e-7

    def f(x, y, d):
        t = distortion_terms(x, y, d)
        return np.stack([t.xd, t.yd], -1)

    f0 = f(x, y, dist)
    np.testing.assert_allclose((f(x + h, y, dist) - f0) / h, J.d_xy[..., 0], atol=1e-6)
    np.testing.assert_allclose((f(x, y + h, dist) - f0) / h, J.d_xy[..., 1], atol=1e-6)
    for k in range(5):
        d = dist.copy()
        d[k] += h
        np.testing.assert_allclose((f(x, y, d) - f0) / h, J.d_dist[..., k], atol=1e-6)
