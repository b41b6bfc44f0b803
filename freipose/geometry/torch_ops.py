"""Differentiable, batched PyTorch camera geometry for the network.

Same conventions as :mod:`freipose.geometry` (mm, world→camera, pixel centres at
integers, OpenCV distortion, skew honoured). Camera parameters are tensors with a
batch and a camera axis: ``K`` (B, C, 3, 3), ``dist`` (B, C, 5), ``R`` (B, C, 3, 3),
``t`` (B, C, 3).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from freipose.geometry.camera import CameraRig


def rig_to_tensors(
    rig: CameraRig, dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu"
) -> dict[str, torch.Tensor]:
    """Stacked rig parameters: ``K`` (C,3,3), ``dist`` (C,5), ``R`` (C,3,3), ``t`` (C,3)."""
    return {
        k: torch.as_tensor(np.ascontiguousarray(getattr(rig, k)), dtype=dtype, device=device)
        for k in ("K", "dist", "R", "t")
    }


def _distortion(
    x: torch.Tensor, y: torch.Tensor, coeffs: Sequence[torch.Tensor], distorted: bool
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The OpenCV distortion polynomial at normalized points, in PyTorch.

    The same polynomial as :func:`freipose.geometry.distortion.distortion_terms`. The
    tangential terms are built lazily so that the operations are recorded in one fixed
    order for each use (autograd sums gradients in the order the operations were made).

    Args:
        x: (...,) normalized x.
        y: (...,) normalized y.
        coeffs: ``dist.unbind(-1)``: the coefficients ``(k1, k2, p1, p2, k3)``, each
            broadcastable to ``x``.
        distorted: return the distorted coordinates ``(xd, yd)`` (True) or only the
            tangential shifts ``(xd - x radial, yd - y radial)`` (False).

    Returns:
        ``(xd, yd, radial)`` or ``(dx, dy, radial)``, each (...,).
    """
    k1, k2, p1, p2, k3 = coeffs
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    tangential = (
        (x, lambda: 2 * p1 * x * y, lambda: p2 * (r2 + 2 * x * x)),
        (y, lambda: p1 * (r2 + 2 * y * y), lambda: 2 * p2 * x * y),
    )
    out = []
    for v, by_p1, by_p2 in tangential:
        if distorted:
            s = v * radial + by_p1()
            out.append(s + by_p2())
        else:
            out.append(by_p1() + by_p2())
    return out[0], out[1], radial


def distort_normalized(xy: torch.Tensor, dist: torch.Tensor) -> torch.Tensor:
    """OpenCV distortion of normalized coordinates (differentiable).

    Args:
        xy: (..., 2) normalized coordinates ``(x/z, y/z)``.
        dist: (..., 5) coefficients ``(k1, k2, p1, p2, k3)``, broadcastable to ``xy``.

    Returns:
        (..., 2) distorted normalized coordinates.
    """
    coeffs = dist.unbind(-1)
    x, y = xy.unbind(-1)
    xd, yd, _ = _distortion(x, y, coeffs, distorted=True)
    return torch.stack([xd, yd], dim=-1)


def undistort_normalized(
    xy_d: torch.Tensor, dist: torch.Tensor, iterations: int = 10
) -> torch.Tensor:
    """Invert OpenCV distortion by fixed-point iteration (differentiable).

    Args:
        xy_d: (..., 2) distorted normalized coordinates.
        dist: (..., 5) coefficients, broadcastable to ``xy_d``.
        iterations: fixed-point iterations.

    Returns:
        (..., 2) undistorted normalized coordinates.
    """
    coeffs = dist.unbind(-1)
    x0, y0 = xy_d.unbind(-1)
    x, y = x0, y0
    for _ in range(iterations):
        dx, dy, radial = _distortion(x, y, coeffs, distorted=False)
        x = (x0 - dx) / radial
        y = (y0 - dy) / radial
    return torch.stack([x, y], dim=-1)


def project(
    points: torch.Tensor,
    K: torch.Tensor,
    R: torch.Tensor,
    t: torch.Tensor,
    dist: torch.Tensor | None = None,
    min_depth: float = 1e-3,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Project world points into many cameras, differentiably.

    Args:
        points: (B, P, 3) world points in mm.
        K: (B, C, 3, 3) intrinsics; any affine K (last row 0 0 1) works, e.g. the
            rotated crop cameras of training augmentation.
        R: (B, C, 3, 3) world→camera rotations.
        t: (B, C, 3) world→camera translations (mm).
        dist: optional (B, C, 5) distortion coefficients.
        min_depth: depths below this (mm) are clamped for the division and flagged.

    Returns:
        ``(uv, in_front)``: pixels (B, C, P, 2) and a boolean mask (B, C, P) of points with
        positive depth. Pixels of points behind a camera are finite but meaningless.
    """
    if points.ndim != 3 or points.shape[-1] != 3:
        raise ValueError(f"points must have shape (B, P, 3), got {tuple(points.shape)}")
    if K.ndim != 4 or K.shape[-2:] != (3, 3) or K.shape[0] != points.shape[0]:
        raise ValueError(f"K must have shape (B, C, 3, 3), got {tuple(K.shape)}")
    Xc = torch.einsum("bcij,bpj->bcpi", R, points) + t[:, :, None, :]  # (B, C, P, 3)
    z = Xc[..., 2]
    in_front = z > min_depth
    zc = torch.where(in_front, z, torch.full_like(z, min_depth))
    xy = Xc[..., :2] / zc[..., None]
    if dist is not None:
        xy = distort_normalized(xy, dist[:, :, None, :])
    # The full 2x3 part of K: also right for the general affine K of rotated crops.
    uv = torch.einsum("bcij,bcpj->bcpi", K[:, :, :2, :2], xy) + K[:, :, None, :2, 2]
    return uv, in_front


def triangulate_weighted(
    points2d: torch.Tensor,
    weights: torch.Tensor,
    K: torch.Tensor,
    R: torch.Tensor,
    t: torch.Tensor,
    eps: float = 1e-9,
) -> torch.Tensor:
    """Differentiable confidence-weighted linear triangulation (pinhole, no distortion).

    Solves the inhomogeneous DLT by weighted normal equations, which has stable gradients
    (unlike an SVD). Pixels must be undistorted (ideal pinhole) pixels.

    Args:
        points2d: (B, C, P, 2) pixels.
        weights: (B, C, P) non-negative confidences (0 skips the view).
        K: (B, C, 3, 3) intrinsics.
        R: (B, C, 3, 3) world→camera rotations.
        t: (B, C, 3) world→camera translations (mm).
        eps: ridge added to the normal matrix (keeps it invertible).

    Returns:
        (B, P, 3) world points in mm.
    """
    Kinv = torch.linalg.inv(K)
    ones = torch.ones_like(points2d[..., :1])
    xyn = torch.einsum("bcij,bcpj->bcpi", Kinv, torch.cat([points2d, ones], -1))
    x, y = xyn[..., 0], xyn[..., 1]  # (B, C, P)
    Rt = torch.cat([R, t[..., None]], dim=-1)  # (B, C, 3, 4)
    r1 = x[..., None] * Rt[:, :, None, 2] - Rt[:, :, None, 0]  # (B, C, P, 4)
    r2 = y[..., None] * Rt[:, :, None, 2] - Rt[:, :, None, 1]
    rows = torch.stack([r1, r2], dim=1)  # (B, 2, C, P, 4)
    w = weights[:, None, :, :, None].clamp_min(0)
    A = rows[..., :3]
    b = -rows[..., 3:]
    AtA = (A[..., :, None] * A[..., None, :] * w[..., None]).sum(dim=(1, 2))  # (B, P, 3, 3)
    Atb = (A * b * w).sum(dim=(1, 2))  # (B, P, 3)
    eye = torch.eye(3, dtype=A.dtype, device=A.device)
    return torch.linalg.solve(AtA + eps * eye, Atb[..., None])[..., 0]
