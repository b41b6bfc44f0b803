"""Unprojection: every view's 2D features sampled at the voxels of the cube, averaged over views.

:func:`unproject` is the reference (``grid_sample`` per view, then the mean over the views
that see each point); :func:`unproject_gather` computes the same volume at the voxels of a
grid as one weighted gather of feature rows (:func:`sampling_plan`, :func:`lattice_pixels`),
the optimized backend's unprojection (:mod:`freipose.nn.fast`).

Crop pixel coordinates use the project convention (pixel centres at integers); a feature
pixel ``j`` covers crop pixels ``[j*s, (j+1)*s)``, so its centre is at ``(j + 0.5) * s -
0.5``, which is ``grid_sample``'s ``align_corners=False``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from freipose.geometry.torch_ops import _distortion
from freipose.nn.geometry import project_affine


def unproject(
    features: torch.Tensor,
    K: torch.Tensor,
    R: torch.Tensor,
    t: torch.Tensor,
    dist: torch.Tensor | None,
    view_mask: torch.Tensor,
    points: torch.Tensor,
    crop_size: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Differentiable inverse projection: sample every view's features at every 3D point.

    Each point is projected with each view's crop camera (distortion included) and the
    view's feature map is sampled bilinearly there. Views whose image does not contain the
    projection (or that are padding, ``view_mask`` False, or see the point from behind)
    do not count; the result is the mean over the views that see the point (0 if none).

    Args:
        features: (B, V, C, h, w) per-view feature maps covering the S x S crops.
        K: (B, V, 3, 3) affine crop intrinsics.
        R: (B, V, 3, 3) camera rotations.
        t: (B, V, 3) camera translations (mm).
        dist: (B, V, 5) distortion coefficients (or None).
        view_mask: (B, V) bool, real views.
        points: (B, P, 3) world mm (voxel centres).
        crop_size: S, crop side in pixels.

    Returns:
        ``(volume, count)``: (B, C, P) mean features and (B, P) number of views seeing it.
    """
    B, V, C, h, w = features.shape
    P = points.shape[1]
    uv, in_front = project_affine(points, K, R, t, dist)  # (B, V, P, 2)
    g = (2.0 * (uv + 0.5) / crop_size - 1.0).to(features.dtype)
    valid = in_front & (g.abs() <= 1).all(-1) & view_mask[:, :, None]
    sampled = F.grid_sample(
        features.reshape(B * V, C, h, w),
        g.reshape(B * V, 1, P, 2),
        mode="bilinear",
        padding_mode="border",
        align_corners=False,
    ).reshape(B, V, C, P)
    valid_f = valid.to(sampled.dtype)
    count = valid_f.sum(1)  # (B, P)
    # view by view: a (B, V, C, P) product would be written and read again in full;
    # unbind, not indexing: its backward stacks the views' gradients once, where each
    # index's backward would zero-fill a whole (B, V, C, P) gradient of its own
    views = sampled.unbind(1)
    total = views[0] * valid_f[:, 0, None, :]
    for v in range(1, V):
        total.addcmul_(views[v], valid_f[:, v, None, :])
    return total / count.clamp_min(1.0)[:, None, :], count


def sampling_plan(
    K: torch.Tensor,
    R: torch.Tensor,
    t: torch.Tensor,
    dist: torch.Tensor | None,
    view_mask: torch.Tensor,
    grid: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    crop_size: int,
    feature_size: tuple[int, int],
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Where :func:`unproject` reads the feature maps for a voxel grid, as table rows and weights.

    The bilinear sample of view v at voxel p (``grid_sample``, ``align_corners=False``,
    border padding) is a weighted sum of four feature pixels; the mean over the views that
    see p is then a weighted sum of ``4 V`` rows of the table of all views' feature pixels
    (``(B*V*h*w, C)``, channels last), with the bilinear weights times ``valid / count``. The
    plan depends only on the cameras and the grid, not on the features.

    Args:
        K: (B, V, 3, 3) affine crop intrinsics.
        R: (B, V, 3, 3) camera rotations.
        t: (B, V, 3) camera translations (mm).
        dist: (B, V, 5) distortion coefficients (or None).
        view_mask: (B, V) bool, real views.
        grid: the voxel grid ``(center, axes, offsets)`` (:func:`lattice_pixels`).
        crop_size: S, crop side in pixels.
        feature_size: (h, w) of the feature maps.

    Returns:
        ``(rows, weights, count)``: (B*P, 4*V) int32 table rows, (B*P, 4*V) float32
        weights and (B, P) number of views seeing each voxel (P = G**3).
    """
    B, V = view_mask.shape
    h, w = feature_size
    ix, iy, in_front = lattice_pixels(K, R, t, dist, grid, crop_size, (h, w))  # (B, P, V)
    valid = in_front & ix.ge(-0.5) & ix.le(w - 0.5) & iy.ge(-0.5) & iy.le(h - 0.5)
    valid &= view_mask[:, None, :]
    count = valid.sum(-1, dtype=torch.float32)  # (B, P)
    scale = valid / count.clamp_min(1.0)[..., None]  # (B, P, V)
    # border padding; the left corner stays one pixel inside, so the four rows are
    # r00 + (0, dx, dy*w, dy*w + dx)
    dx, dy = int(w > 1), int(h > 1)
    ix = ix.clamp_(0, w - 1)
    iy = iy.clamp_(0, h - 1)
    x0 = ix.floor().clamp_(max=w - 1 - dx)
    y0 = iy.floor().clamp_(max=h - 1 - dy)
    wx1 = ix.sub_(x0)
    wy1 = iy.sub_(y0).mul_(scale)  # the rows of y1, valid / count included
    wy0 = scale.sub_(wy1)
    wx0 = 1 - wx1
    first = torch.arange(B * V, device=K.device, dtype=torch.int32).reshape(B, 1, V) * (h * w)
    r00 = y0.mul_(w).add_(x0).to(torch.int32).add_(first)  # (B, P, V)
    # (B, P, V, 4) in the bags' order, each corner written in place (a broadcast over a
    # last axis of 4 would be laid out corner-major and copied)
    weights = torch.empty(r00.shape + (4,), dtype=torch.float32, device=K.device)
    rows = torch.empty(r00.shape + (4,), dtype=torch.int32, device=K.device)
    corners = ((wy0, wx0, 0), (wy0, wx1, dx), (wy1, wx0, dy * w), (wy1, wx1, dy * w + dx))
    for c, (wy, wx, offset) in enumerate(corners):
        torch.mul(wy, wx, out=weights[..., c])
        torch.add(r00, offset, out=rows[..., c])
    return rows.reshape(-1, 4 * V), weights.reshape(-1, 4 * V), count


def lattice_pixels(
    K: torch.Tensor,
    R: torch.Tensor,
    t: torch.Tensor,
    dist: torch.Tensor | None,
    grid: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    crop_size: int,
    feature_size: tuple[int, int],
    min_depth: float = 1e-3,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Feature-pixel coordinates of every voxel of a grid in every view (planar, fp32).

    Voxel ``(i, j, k)`` (flat index ``i*G*G + j*G + k``) sits at ``center + axes @ (o[i],
    o[j], o[k])``; its camera coordinates ``R (center + axes @ o) + t`` are a sum of one (G,)
    term per grid axis, so each costs one broadcast sum. The projection is that of
    :func:`freipose.geometry.torch_ops.project` (distortion included, skipped when every
    coefficient is zero), followed by ``grid_sample``'s unnormalisation ``(u + 0.5) * w / S
    - 0.5``.

    Args:
        K: (B, V, 3, 3) affine crop intrinsics.
        R: (B, V, 3, 3) camera rotations.
        t: (B, V, 3) camera translations (mm).
        dist: (B, V, 5) distortion coefficients (or None).
        grid: ``(center, axes, offsets)``: (B, 3) cube centres (world mm), (B, 3, 3) world
            directions of the grid's index axes (columns) and (G,) voxel offsets along an
            axis in mm (:func:`freipose.nn.geometry.voxel_axis`).
        crop_size: S.
        feature_size: (h, w).
        min_depth: depths below this (mm) count as behind the camera.

    Returns:
        ``(ix, iy, in_front)``: (B, G**3, V) feature-pixel x and y and the mask of voxels in
        front of the camera.
    """
    center, axes, offsets = (v.float() for v in grid)
    B, V = K.shape[:2]
    G = offsets.shape[0]
    h, w = feature_size
    K, R, t = K.float(), R.float(), t.float()
    M = R @ axes[:, None]  # (B, V, 3, 3): camera coordinates per unit step along each axis
    base = (R @ center[:, None, :, None])[..., 0] + t  # (B, V, 3)
    # camera coordinate c of voxel (i, j, k): base_c + o_i M[c, 0] + o_j M[c, 1] + o_k M[c, 2],
    # built as (B, 3, G, G, G, V): the views last, as the gather's bags want them
    steps = (M[..., None] * offsets).permute(0, 2, 3, 4, 1)  # (B, 3, 3, G, V)
    first_two = steps[:, :, 0, :, None] + (steps[:, :, 1, None] + base.mT[:, :, None, None])
    cam = (first_two[:, :, :, :, None] + steps[:, :, 2, None, None]).reshape(B, 3, G**3, V)
    x, y, z = cam.unbind(1)
    in_front = z > min_depth
    inv = torch.where(in_front, z, torch.full_like(z, min_depth)).reciprocal_()
    x = x.mul_(inv)
    y = y.mul_(inv)
    if dist is not None and bool(dist.any()):
        x, y, _ = _distortion(x, y, dist.float()[:, None].unbind(-1), distorted=True)
    # (u + 0.5) * w / S - 0.5 with u = K[0,0] x + K[0,1] y + K[0,2]
    sx, sy = w / crop_size, h / crop_size
    ku = (K[:, :, 0, :] * sx)[:, None]  # (B, 1, V, 3)
    kv = (K[:, :, 1, :] * sy)[:, None]
    ix = (x * ku[..., 0]).addcmul_(y, ku[..., 1]).add_(ku[..., 2] + 0.5 * sx - 0.5)
    iy = (x * kv[..., 0]).addcmul_(y, kv[..., 1]).add_(kv[..., 2] + 0.5 * sy - 0.5)
    return ix, iy, in_front


def unproject_gather(
    features: torch.Tensor,
    K: torch.Tensor,
    R: torch.Tensor,
    t: torch.Tensor,
    dist: torch.Tensor | None,
    view_mask: torch.Tensor,
    grid: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    crop_size: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`unproject` at the voxels of a grid, as one weighted gather of feature rows.

    The same mean of bilinear samples (fp32 rounding apart, the same volume), computed by
    one ``embedding_bag`` over the channels-last table of feature pixels
    (:func:`sampling_plan`) instead of ``grid_sample``, a (B, V, C, P) intermediate and a
    loop over the views. Differentiable in ``features``.

    Args:
        features: (B, V, C, h, w) per-view feature maps (any memory layout; channels last
            avoids a copy).
        K: (B, V, 3, 3) affine crop intrinsics.
        R: (B, V, 3, 3) camera rotations.
        t: (B, V, 3) camera translations (mm).
        dist: (B, V, 5) distortion coefficients (or None).
        view_mask: (B, V) bool, real views.
        grid: the voxel grid ``(center, axes, offsets)`` (:func:`lattice_pixels`).
        crop_size: S, crop side in pixels.

    Returns:
        ``(volume, count)``: (B, C, P) mean features (a view of a channels-last (B, P, C)
        tensor) and (B, P) number of views seeing each voxel.
    """
    B, V, C, h, w = features.shape
    rows, weights, count = sampling_plan(K, R, t, dist, view_mask, grid, crop_size, (h, w))
    table = features.permute(0, 1, 3, 4, 2).reshape(B * V * h * w, C)
    out = F.embedding_bag(rows, table, mode="sum", per_sample_weights=weights.to(table.dtype))
    return out.reshape(B, -1, C).transpose(1, 2), count
