"""Training losses, every term masked by label visibility (the original did not mask).

Each term is normalised per sample (sum of masked errors over the number of valid
entries of that sample) and then averaged over the batch, so that DDP's gradient averaging
over equally sized per-process batches equals one process with the whole batch.
3D errors are Euclidean distances in voxel units (mm / voxel size), 2D errors Euclidean
distances in feature pixels (crop px / stride).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
import torch.nn.functional as F

from freipose.nn.config import ModelConfig, ScheduleConfig
from freipose.nn.geometry import voxel_axis
from freipose.nn.layers import gaussian_log_prior


def _masked_mean(err: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-sample mean of ``err`` over ``mask`` (both (B, ...)), then mean over samples."""
    m = mask.to(err.dtype)
    dims = tuple(range(1, err.ndim))
    per = (err * m).sum(dims) / m.sum(dims).clamp_min(1.0)
    return per.mean()


def point_error(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Euclidean distance with a smooth minimum (differentiable at 0). (..., D) -> (...)."""
    return torch.sqrt(((pred.float() - gt.float()) ** 2).sum(-1) + 1e-6)


def volume_cross_entropy(
    probs: torch.Tensor,
    gt: torch.Tensor,
    mask: torch.Tensor,
    center: torch.Tensor,
    rotation: torch.Tensor | None,
    model: ModelConfig,
) -> torch.Tensor:
    """Cross-entropy of the score volumes against a Gaussian around the 3D labels.

    The target is a normalised Gaussian of ``model.volume_sigma`` voxels around each label
    (in the grid's own axes); labels outside the cube are not counted. It makes the score
    volumes peaked and unimodal, which the L1 loss on the soft-argmax alone does not.

    Args:
        probs: (B, K, G**3) softmax of the final score volumes.
        gt: (B, K, 3) labels (mm).
        mask: (B, K) bool, labeled keypoints.
        center: (B, 3) cube centres (mm).
        rotation: (B, 3, 3) orientations of the grid axes in the world (or None).
        model: gives the grid, the cube and ``volume_sigma``.

    Returns:
        Scalar loss (nats), per-sample mean over the valid keypoints, mean over samples.
    """
    G = model.grid_size
    vs = model.voxel_size
    rel = gt.float() - center.float()[:, None, :]
    if rotation is not None:
        rel = rel @ rotation.float()  # world offsets -> grid axes (R^T applied per row)
    half = model.cube_size / 2
    inside = (rel.abs() <= half).all(-1) & mask
    # the Gaussian is a product of one factor per grid axis, and so is its normalisation:
    # three (B, K, G) softmaxes and their outer product
    ax = voxel_axis(G, model.cube_size, device=probs.device)
    d2 = (ax[None, None, None, :] - rel[..., None]) ** 2 / (vs * vs)  # (B, K, 3, G)
    f = torch.softmax(-d2 / (2 * model.volume_sigma**2), dim=-1)
    target = f[:, :, 0, :, None, None] * f[:, :, 1, None, :, None] * f[:, :, 2, None, None, :]
    target = target.reshape(*f.shape[:2], -1)  # (B, K, G^3)
    ce = -(target * torch.log(probs.float().clamp_min(1e-12))).sum(-1)  # (B, K)
    return _masked_mean(ce, inside)


def map_cross_entropy(
    logits: torch.Tensor, gt2d: torch.Tensor, visible: torch.Tensor, model: ModelConfig
) -> torch.Tensor:
    """Cross-entropy of the 2D heads' maps against a Gaussian around the visible 2D labels.

    The target is a normalised Gaussian of ``model.map_sigma`` map pixels around each label
    (labels outside the map are not counted). Like :func:`volume_cross_entropy` for the score
    volumes, it makes the maps peaked, which the soft-argmax point loss alone does not.

    Args:
        logits: (B, V, K, H, W) map logits (those the soft-argmax decodes).
        gt2d: (B, V, K, 2) crop pixels.
        visible: (B, V, K) bool, visible labels.
        model: gives the map stride and ``map_sigma``.

    Returns:
        Scalar loss (nats), per-sample mean over the visible entries, mean over samples.
    """
    size = logits.shape[-1]  # square maps
    ms = model.map_stride
    f = (gt2d.float() + 0.5) / ms - 0.5  # map px
    inside = visible & (f >= -0.5).all(-1) & (f <= size - 0.5).all(-1)
    uv = torch.nan_to_num(gt2d.float(), nan=0.0)
    prior = gaussian_log_prior(uv.flatten(0, 1), size, ms, model.map_sigma)
    target = torch.softmax(prior.reshape(*uv.shape[:3], -1), dim=-1)
    logp = torch.log_softmax(logits.float().flatten(-2), dim=-1)
    ce = -(target * logp).sum(-1)  # (B, V, K)
    return _masked_mean(ce, inside)


def voxel_losses(
    out: Mapping[str, Any],
    batch: Mapping[str, Any],
    model: ModelConfig,
    sched: ScheduleConfig,
    refine_on: bool,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Total loss and its parts for :class:`freipose.nn.model.VoxelPoseNet`.

    Terms: ``p0`` (final P0 vs 3D labels), ``aux`` (mean over deep-supervision decodings), ``vol``
    (:func:`volume_cross_entropy` of the final score volume), ``2d`` (refined 2D points vs visible
    2D labels), ``conf`` (per-view confidence, binary cross-entropy against ``visible * exp(-e^2 /
    2)`` with ``e`` the refined 2D error in feature pixels), ``map`` (:func:`map_cross_entropy`
    of the refinement maps), ``p1`` (P1 vs 3D labels). The refinement terms are weighted 0
    until ``refine_on``.
    """
    gt3, m3 = batch["points3d"], batch["mask3d"]
    vs = model.voxel_size
    parts: dict[str, torch.Tensor] = {}
    parts["p0"] = _masked_mean(point_error(out["P0"], gt3) / vs, m3)
    aux = out.get("P0_aux") or []
    parts["aux"] = (
        torch.stack([_masked_mean(point_error(p, gt3) / vs, m3) for p in aux]).mean()
        if aux
        else torch.zeros((), device=gt3.device)
    )
    total = sched.weight_p0 * parts["p0"] + sched.weight_aux * parts["aux"]
    if sched.weight_volume > 0 and "volume_probs" in out:
        parts["vol"] = volume_cross_entropy(
            out["volume_probs"], gt3, m3, batch["center"], batch.get("grid_rotation"), model
        )
        total = total + sched.weight_volume * parts["vol"]
    if model.refine:
        w = 1.0 if refine_on else 0.0
        vis = batch["visible2d"] & batch["view_mask"][:, :, None]
        e2 = point_error(out["points2d"], batch["points2d"]) / model.stride
        parts["2d"] = _masked_mean(e2, vis)
        target = (vis.float() * torch.exp(-0.5 * e2.detach() ** 2)).clamp(0, 1)
        cmask = batch["view_mask"][:, :, None] & m3[:, None, :]
        bce = F.binary_cross_entropy(
            out["confidence2d"].float().clamp(1e-6, 1 - 1e-6), target, reduction="none"
        )
        parts["conf"] = _masked_mean(bce, cmask)
        parts["p1"] = _masked_mean(point_error(out["P1"], gt3) / vs, m3)
        parts["map"] = map_cross_entropy(out["map_logits"], batch["points2d"], vis, model)
        total = total + w * (
            sched.weight_map * parts["map"]
            + sched.weight_2d * parts["2d"]
            + sched.weight_conf * parts["conf"]
            + sched.weight_p1 * parts["p1"]
        )
    return total, {k: float(v.detach()) for k, v in parts.items()}


def baseline_losses(
    out: Mapping[str, Any], batch: Mapping[str, Any], model: ModelConfig, sched: ScheduleConfig
) -> tuple[torch.Tensor, dict[str, float]]:
    """Loss of :class:`freipose.nn.model.BaselineNet`: 2D error, confidence, map cross-entropy.

    The terms are those of :func:`voxel_losses` of the same names.

    Args:
        out: the network's output.
        batch: the collated batch (with labels).
        model: the architecture.
        sched: gives the terms' weights.

    Returns:
        ``(total, parts)``: the weighted sum and the terms ``2d``, ``conf`` and ``map``.
    """
    vis = batch["visible2d"] & batch["view_mask"][:, :, None]
    e2 = point_error(out["points2d"], batch["points2d"]) / model.stride
    l2d = _masked_mean(e2, vis)
    target = (vis.float() * torch.exp(-0.5 * e2.detach() ** 2)).clamp(0, 1)
    cmask = batch["view_mask"][:, :, None] & batch["mask3d"][:, None, :]
    bce = F.binary_cross_entropy(
        out["confidence2d"].float().clamp(1e-6, 1 - 1e-6), target, reduction="none"
    )
    lconf = _masked_mean(bce, cmask)
    lmap = map_cross_entropy(out["map_logits"], batch["points2d"], vis, model)
    total = sched.weight_2d * l2d + sched.weight_conf * lconf + sched.weight_map * lmap
    return total, {
        "2d": float(l2d.detach()),
        "conf": float(lconf.detach()),
        "map": float(lmap.detach()),
    }
