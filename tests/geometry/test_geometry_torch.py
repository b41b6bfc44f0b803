"""Differentiable PyTorch geometry agrees with NumPy and has correct gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from freipose.geometry import project_rig, triangulate_weighted, undistort_pixels
from freipose.geometry import torch_ops as T


def test_project_matches_numpy(distorted_rig, rng):
    X = rng.uniform(-150, 150, size=(2, 7, 3))
    p = T.rig_to_tensors(distorted_rig, dtype=torch.float64)
    B = 2
    K, R, t, d = (p[k].expand(B, *p[k].shape) for k in ("K", "R", "t", "dist"))
    uv, front = T.project(torch.as_tensor(X), K, R, t, d)
    assert uv.shape == (2, 6, 7, 2) and front.all()
    np.testing.assert_allclose(uv.numpy(), project_rig(X, distorted_rig), atol=1e-8)
    uv0, _ = T.project(torch.as_tensor(X), K, R, t, None)
    np.testing.assert_allclose(uv0.numpy(), project_rig(X, distorted_rig, distort=False), atol=1e-8)


def test_project_flags_points_behind(circle_rig):
    p = T.rig_to_tensors(circle_rig, dtype=torch.float64)
    behind = torch.as_tensor(2 * circle_rig[0].center)[None, None]  # beyond camera 0
    uv, front = T.project(behind, p["K"][None], p["R"][None], p["t"][None])
    assert not front[0, 0, 0] and front[0, 3, 0]  # the opposite camera sees it
    assert torch.isfinite(uv).all()


def test_project_gradcheck(rng):
    torch.manual_seed(0)
    X = torch.tensor(rng.uniform(-50, 50, size=(1, 3, 3)), dtype=torch.float64, requires_grad=True)
    K = torch.tensor(
        [[[[800.0, 2.0, 320.0], [0.0, 790.0, 240.0], [0.0, 0.0, 1.0]]]],
        dtype=torch.float64,
        requires_grad=True,
    )
    R = torch.eye(3, dtype=torch.float64)[None, None]
    t = torch.tensor([[[10.0, -5.0, 600.0]]], dtype=torch.float64, requires_grad=True)
    d = torch.tensor([[[-0.2, 0.05, 0.001, -0.002, 0.01]]], dtype=torch.float64, requires_grad=True)

    def f(X, K, t, d):
        return T.project(X, K, R, t, d)[0]

    assert torch.autograd.gradcheck(f, (X, K, t, d), eps=1e-6, atol=1e-5)


def test_triangulate_weighted_matches_numpy(distorted_rig, rng):
    X = rng.uniform(-150, 150, size=(2, 9, 3))
    uv = project_rig(X, distorted_rig)  # (B, C, P, 2) distorted pixels
    ideal = np.stack(
        [undistort_pixels(uv[:, i], c, to_pixels=True) for i, c in enumerate(distorted_rig)], 1
    )
    w = rng.uniform(0.2, 1.0, size=(2, 6, 9))
    w[0, :4, 0] = 0.0  # only two views for one point
    p = T.rig_to_tensors(distorted_rig, dtype=torch.float64)
    K, R, t = (p[k].expand(2, *p[k].shape) for k in ("K", "R", "t"))
    out = T.triangulate_weighted(torch.as_tensor(ideal), torch.as_tensor(w), K, R, t)
    assert out.shape == (2, 9, 3)
    np.testing.assert_allclose(out.numpy(), X, atol=1e-6)
    ref = triangulate_weighted(np.moveaxis(uv, 1, 2), np.moveaxis(w, 1, 2), distorted_rig)
    np.testing.assert_allclose(out.numpy(), ref, atol=1e-6)
    # With pixel noise the two linear solvers stay close.
    noisy = ideal + rng.normal(0, 0.5, size=ideal.shape)
    out_n = T.triangulate_weighted(
        torch.as_tensor(noisy), torch.ones(2, 6, 9, dtype=torch.float64), K, R, t
    ).numpy()
    assert np.abs(out_n - X).max() < 3.0


def test_triangulate_weighted_has_gradients(circle_rig, rng):
    X = rng.uniform(-50, 50, size=(1, 2, 3))
    uv = torch.as_tensor(project_rig(X, circle_rig), dtype=torch.float64).requires_grad_(True)
    w = torch.ones(1, 6, 2, dtype=torch.float64, requires_grad=True)
    p = T.rig_to_tensors(circle_rig, dtype=torch.float64)
    out = T.triangulate_weighted(uv, w, p["K"][None], p["R"][None], p["t"][None])
    out.sum().backward()
    assert torch.isfinite(uv.grad).all() and uv.grad.abs().sum() > 0
    assert torch.isfinite(w.grad).all()


def test_torch_shape_errors(circle_rig):
    p = T.rig_to_tensors(circle_rig)
    with pytest.raises(ValueError, match=r"\(B, P, 3\)"):
        T.project(torch.zeros(4, 3), p["K"][None], p["R"][None], p["t"][None])
    with pytest.raises(ValueError, match=r"\(B, C, 3, 3\)"):
        T.project(torch.zeros(1, 4, 3), p["K"], p["R"][None], p["t"][None])
