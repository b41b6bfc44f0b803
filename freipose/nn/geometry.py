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

from freipose.geometry.torch_ops import project, undistort_normalized

# Projection with a general affine K is the project-wide torch projection.
project_affine = project


def pixels_to_normalized(
    uv: torch.Tensor, K: torch.Tensor, dist: torch.Tensor | None
) -> torch.Tensor:
    """Undistorted normalized coordinates of crop pixels.

    Args:
        uv: (B, C, P, 2) pixels of cameras with affine intrinsics ``K``.
        K: (B, C, 3, 3) affine intrinsics (last row ``0 0 1``).
        dist: (B, C, 5) distortion coefficients, or None.

    Returns:
        (B, C, P, 2) ideal pinhole coordinates ``(x/z, y/z)``.
    """
    A = K[:, :, :2, :2]
    Ainv = torch.linalg.inv(A)
    xy = torch.einsum("bcij,bcpj->bcpi", Ainv, uv - K[:, :, None, :2, 2])
    if dist is not None:
        xy = undistort_normalized(xy, dist[:, :, None, :])
    return xy


def ray_distances(
    points: torch.Tensor,
    uv: torch.Tensor,
    K: torch.Tensor,
    R: torch.Tensor,
    t: torch.Tensor,
    dist: torch.Tensor | None,
) -> torch.Tensor:
    """Distance in mm of 3D points from the rays of their 2D observations, at their depth.

    Args:
        points: (B, P, 3) world mm.
        uv: (B, C, P, 2) observed crop pixels of the points in each camera.
        K: (B, C, 3, 3) affine intrinsics.
        R: (B, C, 3, 3) camera rotations.
        t: (B, C, 3) camera translations (mm).
        dist: (B, C, 5) distortion coefficients, or None.

    Returns:
        (B, C, P) lateral distance of each point from each camera's ray through its
        observation, in mm at the point's depth (the DLT residual of
        :func:`freipose.nn.layers.triangulate_with_prior`).
    """
    xy = pixels_to_normalized(uv.float(), K.float(), None if dist is None else dist.float())
    return normalized_ray_distances(points, xy, R, t)


def normalized_ray_distances(
    points: torch.Tensor, xy: torch.Tensor, R: torch.Tensor, t: torch.Tensor
) -> torch.Tensor:
    """:func:`ray_distances` of observations already in undistorted normalized coordinates.

    Args:
        points: (B, P, 3) world mm.
        xy: (B, C, P, 2) float32 from :func:`pixels_to_normalized`.
        R: (B, C, 3, 3) camera rotations.
        t: (B, C, 3) camera translations (mm).

    Returns:
        (B, C, P) distances in mm.
    """
    cam = torch.einsum("bcij,bpj->bcpi", R.float(), points.float()) + t.float()[:, :, None]
    z = cam[..., 2]
    return (xy * z[..., None] - cam[..., :2]).norm(dim=-1)


def voxel_axis(
    grid_size: int,
    cube_size: float,
    device: str | torch.device | None = None,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """Offsets in mm of the voxel centres from the cube centre along one grid axis.

    Returns:
        (G,) offsets ``(index - (G - 1) / 2) * cube_size / (G - 1)``.
    """
    s = cube_size / (grid_size - 1)
    return (torch.arange(grid_size, device=device, dtype=dtype) - (grid_size - 1) / 2) * s


def voxel_offsets(
    grid_size: int,
    cube_size: float,
    device: str | torch.device | None = None,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """Offsets in mm of the voxel centres from the cube centre.

    Voxel ``(i, j, k)`` (x, y, z indices, flat index ``i*G*G + j*G + k``) sits at
    ``centre + (index - (G - 1) / 2) * cube_size / (G - 1)``.

    Args:
        grid_size: voxels ``G`` per cube edge.
        cube_size: cube edge length in mm.
        device: the tensor's device.
        dtype: the tensor's dtype.

    Returns:
        (G**3, 3) offsets in mm.
    """
    ax = voxel_axis(grid_size, cube_size, device, dtype)
    gx, gy, gz = torch.meshgrid(ax, ax, ax, indexing="ij")
    return torch.stack([gx, gy, gz], dim=-1).reshape(-1, 3)
