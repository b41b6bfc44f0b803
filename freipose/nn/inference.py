"""Batch inference: trained networks on collated batches or on full frames and cube centres.

:func:`predict_prepared` runs a network on a collated :class:`~freipose.nn.types.Batch`
(bfloat16 autocast on CUDA) and maps its outputs to world mm and full-image pixels; for
the baseline the 3D points come from robust triangulation of the per-view predictions
(:func:`triangulate_baseline`). :func:`predict_batch` crops full frames around given cube
centres first.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from freipose.geometry.camera import CameraRig
from freipose.geometry.triangulation import triangulate_robust
from freipose.nn.config import ModelConfig
from freipose.nn.data import collate_prepared, prepare_sample, to_device
from freipose.nn.fast import inference_autocast
from freipose.nn.model import BaselineNet, VoxelPoseNet
from freipose.nn.types import Batch, Prediction, Sample


def crop_to_image(points2d: np.ndarray, affine: np.ndarray) -> np.ndarray:
    """Map crop pixels back to full-image pixels.

    Args:
        points2d: (..., V, K, 2) crop pixels.
        affine: (..., V, 3, 3) full-image to crop pixel maps.

    Returns:
        (..., V, K, 2) full-image pixels.
    """
    inv = np.linalg.inv(affine)
    hom = np.concatenate([points2d, np.ones(points2d.shape[:-1] + (1,))], -1)
    return np.einsum("...vij,...vkj->...vki", inv, hom)[..., :2]


def triangulate_baseline(
    points2d: np.ndarray,
    confidence2d: np.ndarray,
    rig: CameraRig,
    min_confidence: float = 0.1,
    threshold: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Robust triangulation of per-view 2D predictions (the Anipose-style baseline).

    Args:
        points2d: (V, K, 2) full-image pixels.
        confidence2d: (V, K) per-view confidences.
        rig: the V cameras.
        min_confidence: views below this confidence are dropped (0.1 as in the paper).
        threshold: RANSAC inlier threshold in pixels (default 2 % of the mean image width).

    Returns:
        ``(points3d, confidence)``: (K, 3) mm (NaN without two consistent views) and (K,)
        mean confidence of the inlier views (0 where not triangulated).
    """
    if threshold is None:
        threshold = 0.02 * float(np.mean([c.width for c in rig]))
    obs = np.where((confidence2d >= min_confidence)[..., None], points2d, np.nan)
    pts = np.moveaxis(obs, 0, 1)  # (K, V, 2)
    w = np.moveaxis(confidence2d, 0, 1)
    if len(rig) < 2:
        return np.full((pts.shape[0], 3), np.nan), np.zeros(pts.shape[0])
    X, inl = triangulate_robust(pts, rig, threshold=threshold, weights=w)
    conf = np.where(inl.any(-1), (w * inl).sum(-1) / np.maximum(inl.sum(-1), 1), 0.0)
    return X, np.where(np.isfinite(X).all(-1), conf, 0.0)


def _triangulate_batch(
    uv: np.ndarray, c2: np.ndarray, rigs: Sequence[CameraRig], min_confidence: float
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`triangulate_baseline` per sample: (B, K, 3) points and (B, K) confidences."""
    points, confidence = [], []
    for i, rig in enumerate(rigs):
        n = len(rig)
        X, c = triangulate_baseline(uv[i, :n], c2[i, :n], rig, min_confidence)
        points.append(X)
        confidence.append(c)
    return np.stack(points), np.stack(confidence)


@torch.no_grad()
def predict_prepared(model: nn.Module, batch: Batch, min_confidence: float = 0.1) -> Prediction:
    """Run a model on a collated batch; outputs in world mm and full-image pixels.

    Args:
        model: a :class:`~freipose.nn.model.VoxelPoseNet` or
            :class:`~freipose.nn.model.BaselineNet` (or a wrapper with ``module``).
        batch: from :func:`freipose.nn.data.collate_prepared` (on the CPU).
        min_confidence: the baseline's triangulation drops views below this confidence.

    Returns:
        The :class:`~freipose.nn.types.Prediction` (NaN / 0 on padding views).
    """
    device = next(model.parameters()).device
    b = to_device(batch, device)
    with inference_autocast(model, device):
        out = model(b)
    mask = batch["view_mask"].numpy()
    aff = batch["affine"].numpy().astype(np.float64)
    uv = crop_to_image(out["points2d"].float().cpu().numpy().astype(np.float64), aff)
    uv[~mask] = np.nan
    c2 = out["confidence2d"].float().cpu().numpy()
    c2 = np.where(mask[..., None], c2, 0.0)
    if isinstance(getattr(model, "module", model), BaselineNet):
        P, conf = _triangulate_batch(uv, c2, batch["rigs"], min_confidence)
        return {"P0": P, "P1": P.copy(), "confidence": conf, "points2d": uv, "confidence2d": c2}
    return {
        "P0": out["P0"].float().cpu().numpy().astype(np.float64),
        "P1": out["P1"].float().cpu().numpy().astype(np.float64),
        "confidence": out["confidence"].float().cpu().numpy(),
        "points2d": uv,
        "confidence2d": c2,
    }


def predict_batch(
    model: VoxelPoseNet | BaselineNet,
    images: Sequence[Sequence[np.ndarray]],
    rigs: Sequence[CameraRig],
    centers: np.ndarray,
    animals: tuple[np.ndarray, np.ndarray] | None = None,
) -> Prediction:
    """Predict poses from full frames and cube centres (e.g. from the detector).

    Args:
        model: from :func:`freipose.nn.checkpoint.load_checkpoint` (voxel network or baseline).
        images: per sample, one BGR uint8 (H, W, 3) full frame per camera of its rig.
        rigs: per sample, the cameras (samples may have different rigs / view counts).
        centers: (B, 3) cube centres in mm; a NaN row gives NaN outputs for that sample.
        animals: with ``model.mask_others``, ``(own, others)``: (B, K, 3) each sample's pose
            and (B, M, K, 3) the other animals' at its instant, from a first pass (NaN
            where unknown); their bodies are painted out (:mod:`freipose.nn.instances`).

    Returns:
        ``P0``, ``P1`` (B, K, 3) world mm, ``confidence`` (B, K) in [0, 1], ``points2d``
        (B, Vmax, K, 2) refined full-image pixels (NaN on padding views), ``confidence2d``
        (B, Vmax, K).

    Raises:
        ValueError: the numbers of image lists, rigs and centres differ.
    """
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    if not (len(images) == len(rigs) == len(centers)):
        raise ValueError(
            f"predict_batch: got {len(images)} image lists, {len(rigs)} rigs and "
            f"{len(centers)} centres; they must match"
        )
    cfg: ModelConfig = model.cfg
    nk = model.num_keypoints
    B = len(centers)
    vmax = max((len(r) for r in rigs), default=0)
    res: Prediction = {
        "P0": np.full((B, nk, 3), np.nan),
        "P1": np.full((B, nk, 3), np.nan),
        "confidence": np.zeros((B, nk)),
        "points2d": np.full((B, vmax, nk, 2), np.nan),
        "confidence2d": np.zeros((B, vmax, nk)),
    }
    ok = [i for i in range(B) if np.all(np.isfinite(centers[i]))]
    if not ok:
        return res
    samples: list[Sample] = [{"rig": rigs[i], "images": list(images[i]), "index": i} for i in ok]
    if animals is not None:
        for s, i in zip(samples, ok, strict=True):
            s["own3d"], s["others3d"] = animals[0][i], animals[1][i]
    items = [prepare_sample(s, cfg, center=centers[i]) for s, i in zip(samples, ok, strict=True)]
    model.eval()
    out = predict_prepared(model, collate_prepared(items))
    v = out["points2d"].shape[1]
    for key in ("P0", "P1", "confidence"):
        res[key][ok] = out[key]  # type: ignore[literal-required]
    res["points2d"][ok, :v] = out["points2d"]
    res["confidence2d"][ok, :v] = out["confidence2d"]
    return res
