"""Torch camera helpers for crop cameras with a general affine intrinsic matrix.

A crop camera is the original camera followed by the affine map from full-image pixels to
crop pixels (crop, resize and, during training, an in-plane rotation/zoom/shift). Its
intrinsic matrix ``Kc = A @ K`` is therefore a general affine 3x3 (last row ``0 0 1``),
which :func:`freipose.geometry.torch_ops.project` handles (it uses the full 2x3 part of
``K``). Distortion acts before ``Kc`` (on normalized coordinates), so cropping leaves it
unchanged.
"""

from __future__ import annotations

import torch

from freipose.geometry.torch_ops import project

# Projection with a general affine K is the project-wide torch projection.
project_affine = project


def undistort_normalized(
    xy_d: torch.Tensor, dist: torch.Tensor, iterations: int = 10
) -> torch.Tensor:
    """Invert OpenCV distortion by fixed-point iteration (differentiable).

    Args:
        xy_d: (..., 2) distorted normalized coordinates.
        dist: (..., 5) broadcastable coefficients.
    """
    k1, k2, p1, p2, k3 = dist.unbind(-1)
    x0, y0 = xy_d.unbind(-1)
    x, y = x0, y0
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x = (x0 - dx) / radial
        y = (y0 - dy) / radial
    return torch.stack([x, y], dim=-1)


def pixels_to_normalized(
    uv: torch.Tensor, K: torch.Tensor, dist: torch.Tensor | None
) -> torch.Tensor:
    """Undistorted normalized coordinates of crop pixels.

    Args:
        uv: (B, C, P, 2) pixels of cameras with affine intrinsics ``K`` (B, C, 3, 3).
        dist: (B, C, 5) or None.

    Returns:
        (B, C, P, 2) ideal pinhole coordinates ``(x/z, y/z)``.
    """
    A = K[:, :, :2, :2]
    Ainv = torch.linalg.inv(A)
    xy = torch.einsum("bcij,bcpj->bcpi", Ainv, uv - K[:, :, None, :2, 2])
    if dist is not None:
        xy = undistort_normalized(xy, dist[:, :, None, :])
    return xy


def voxel_offsets(
    grid_size: int, cube_size: float, device=None, dtype=torch.float32
) -> torch.Tensor:
    """Offsets (G**3, 3) in mm of the voxel centres from the cube centre.

    Voxel ``(i, j, k)`` (x, y, z indices, flat index ``i*G*G + j*G + k``) sits at
    ``centre + (index - (G - 1) / 2) * cube_size / (G - 1)``.
    """
    s = cube_size / (grid_size - 1)
    ax = (torch.arange(grid_size, device=device, dtype=dtype) - (grid_size - 1) / 2) * s
    gx, gy, gz = torch.meshgrid(ax, ax, ax, indexing="ij")
    return torch.stack([gx, gy, gz], dim=-1).reshape(-1, 3)
