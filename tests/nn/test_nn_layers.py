"""Unit tests of the voxel-network building blocks on random tensors."""

from __future__ import annotations

import numpy as np
import torch

from freipose.geometry import project
from freipose.geometry.crops import crop_camera, cube_crop_boxes
from freipose.nn.geometry import pixels_to_normalized, project_affine, voxel_offsets
from freipose.nn.layers import (
    gaussian_heatmaps,
    softargmax2d,
    softargmax3d,
    triangulate_with_prior,
    unproject,
    volume_confidence,
)
from freipose.testing import make_circle_rig


def _bilinear_border(fmap: np.ndarray, fx: float, fy: float) -> np.ndarray:
    """Reference bilinear sample of (C, h, w) at feature coords, border-clamped."""
    C, h, w = fmap.shape
    fx = min(max(fx, 0.0), w - 1.0)
    fy = min(max(fy, 0.0), h - 1.0)
    x0, y0 = int(np.floor(fx)), int(np.floor(fy))
    x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
    ax, ay = fx - x0, fy - y0
    return (
        fmap[:, y0, x0] * (1 - ax) * (1 - ay)
        + fmap[:, y0, x1] * ax * (1 - ay)
        + fmap[:, y1, x0] * (1 - ax) * ay
        + fmap[:, y1, x1] * ax * ay
    )


def test_unproject_matches_slow_loop(rng):
    rig = make_circle_rig(n=3, distortion=True)
    S, stride, C = 32, 4, 5
    h = S // stride
    B = 2
    centers = rng.normal(0, 30, size=(B, 3))
    cams = [
        [crop_camera(cam, box, S) for cam, box in zip(rig, cube_crop_boxes(rig, c, 300.0))]
        for c in centers
    ]
    feats = rng.normal(size=(B, 3, C, h, h)).astype(np.float32)
    view_mask = np.array([[True, True, True], [True, False, True]])
    # points: voxel grid plus some far outside every crop
    offs = voxel_offsets(4, 400.0, dtype=torch.float64).numpy()
    pts = np.stack([c + offs for c in centers])
    pts[:, :5] += np.array([900.0, 0, 0])
    K = torch.tensor(np.array([[c.K for c in row] for row in cams]), dtype=torch.float32)
    R = torch.tensor(np.array([[c.R for c in row] for row in cams]), dtype=torch.float32)
    t = torch.tensor(np.array([[c.t for c in row] for row in cams]), dtype=torch.float32)
    d = torch.tensor(np.array([[c.dist for c in row] for row in cams]), dtype=torch.float32)
    vol, count = unproject(
        torch.from_numpy(feats),
        K,
        R,
        t,
        d,
        torch.from_numpy(view_mask),
        torch.tensor(pts, dtype=torch.float32),
        S,
    )
    ref = np.zeros((B, C, pts.shape[1]))
    ref_count = np.zeros((B, pts.shape[1]))
    for b in range(B):
        for p in range(pts.shape[1]):
            acc = np.zeros(C)
            n = 0
            for v in range(3):
                if not view_mask[b, v]:
                    continue
                u = project(pts[b, p], cams[b][v])
                if not np.all(np.isfinite(u)) or not np.all((u >= -0.5) & (u <= S - 0.5)):
                    continue
                f = (u + 0.5) / stride - 0.5
                acc += _bilinear_border(feats[b, v], f[0], f[1])
                n += 1
            ref[b, :, p] = acc / max(n, 1)
            ref_count[b, p] = n
    np.testing.assert_array_equal(count.numpy(), ref_count)
    assert ref_count.min() == 0 and ref_count.max() == 3  # both cases exercised
    np.testing.assert_allclose(vol.numpy(), ref, atol=2e-4)


def test_peaked_volume_decodes_to_voxel_centre():
    G, cube = 8, 400.0
    center = torch.tensor([[10.0, -20.0, 35.0], [0.0, 0.0, 0.0]])
    logits = torch.full((2, 3, G, G, G), -50.0)
    idx = [(1, 2, 3), (7, 0, 4), (3, 3, 3)]
    for k, (i, j, l) in enumerate(idx):
        logits[:, k, i, j, l] = 50.0
    pts, probs = softargmax3d(logits, center, cube)
    s = cube / (G - 1)
    for k, ijk in enumerate(idx):
        expect = center + (torch.tensor(ijk, dtype=torch.float32) - (G - 1) / 2) * s
        torch.testing.assert_close(pts[:, k], expect, atol=1e-3, rtol=0)
    np.testing.assert_allclose(volume_confidence(probs, G).numpy(), 1.0, atol=1e-5)
    flat = volume_confidence(torch.full_like(probs, 1.0 / G**3), G)
    assert float(flat.max()) < 0.1


def test_softargmax2d_and_heatmap_round_trip():
    stride, size = 4.0, 16
    uv = torch.tensor([[[10.3, 40.7], [0.0, 63.0]]])
    heat = gaussian_heatmaps(uv, size, stride, sigma=0.6)
    dec, _ = softargmax2d(torch.log(heat + 1e-12) * 1.0, stride)
    # a sampled gaussian's soft-argmax is its centre away from the borders
    torch.testing.assert_close(dec[0, 0], uv[0, 0], atol=0.05, rtol=0)


def test_triangulation_with_prior(circle_rig, rng):
    rig = make_circle_rig(n=4, distortion=True)
    X = torch.tensor(rng.normal(0, 50, size=(1, 5, 3)), dtype=torch.float32)
    t = {
        k: torch.tensor(getattr(rig, k), dtype=torch.float32)[None] for k in ("K", "R", "t", "dist")
    }
    uv, _ = project_affine(X, t["K"], t["R"], t["t"], t["dist"])
    w = torch.ones(1, 4, 5)
    prior = X + 30.0
    Xh = triangulate_with_prior(uv, w, t["K"], t["R"], t["t"], t["dist"], prior)
    torch.testing.assert_close(Xh, X, atol=0.05, rtol=0)
    # a single view: the point on that view's ray nearest the prior
    w1 = torch.zeros(1, 4, 5)
    w1[:, 0] = 1.0
    X1 = triangulate_with_prior(uv, w1, t["K"], t["R"], t["t"], t["dist"], prior)
    uv1, _ = project_affine(X1, t["K"], t["R"], t["t"], t["dist"])
    torch.testing.assert_close(uv1[:, 0], uv[:, 0], atol=0.05, rtol=0)
    assert float((X1 - X).norm(dim=-1).max()) < float((prior - X).norm(dim=-1).max())
    # undistortion inverts distortion
    xy = pixels_to_normalized(uv, t["K"], t["dist"])
    Xc = torch.einsum("bcij,bpj->bcpi", t["R"], X) + t["t"][:, :, None]
    torch.testing.assert_close(xy, Xc[..., :2] / Xc[..., 2:], atol=1e-5, rtol=0)
