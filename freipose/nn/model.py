"""The FreiPose voxel network, the triangulation baseline, checkpoints and batch prediction.

:class:`VoxelPoseNet` (Section 5.3 of the method): a shared 2D encoder per view crop,
unprojection of the features (optionally raised to a finer stride with the encoder's skip
maps, ``unproject_levels``) into a voxel cube around the animal (mean over the views that
see each voxel), a 3D U-Net giving one score volume per keypoint, soft-argmax to the
initial pose P0 (world mm), then a 2D refinement head per view (features + Gaussian heat
maps of the projected P0) whose refined 2D points and per-view confidences are fused into
P1 by confidence-weighted triangulation anchored to P0 (P0 counts with a learnt multiple of
the views' total confidence, one per keypoint, so P1 moves from P0 only as far as the refined
views agree and the refinement has earned for that keypoint).
The refinement is residual: its map logits are added to a Gaussian log-prior around the
projected P0, so an untrained head reproduces P0 and training learns corrections; with a
single view the fusion keeps P0's depth (eq. 5.3).

:class:`BaselineNet`: the comparison the paper makes (DeepLabCut + triangulation): the same
encoder and 2D head predict every view's keypoints independently; 3D comes from robust
RANSAC triangulation (:func:`triangulate_baseline`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from freipose.geometry.camera import CameraRig
from freipose.geometry.triangulation import triangulate_robust
from freipose.nn.config import ModelConfig, TrainConfig, config_from_dict
from freipose.nn.geometry import project_affine, voxel_offsets
from freipose.nn.layers import (
    Encoder2D,
    FeatureDecoder,
    Head2D,
    UNet3D,
    decode_head,
    gaussian_heatmaps,
    gaussian_log_prior,
    softargmax3d,
    triangulate_with_prior,
    unproject,
    volume_confidence,
)

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "freipose.pose_checkpoint"
CHECKPOINT_VERSION = 2
FUSION_LR_SCALE = 10.0  # learning-rate multiplier of the P1 fusion weights
# version 1: the 2D heads had one decoder level and the config no ``head_levels``


class CheckpointError(ValueError):
    """A checkpoint file is missing, corrupt or of another kind (the message says which)."""


def top2_mean(conf: torch.Tensor, view_mask: torch.Tensor) -> torch.Tensor:
    """Per-keypoint confidence from per-view ones: mean of the two most confident views.

    Args:
        conf: (B, V, K) in [0, 1]; view_mask (B, V).

    Returns:
        (B, K) in [0, 1] (a 3D point needs two agreeing views).
    """
    c = torch.where(view_mask[:, :, None], conf, torch.zeros_like(conf))
    if c.shape[1] == 1:
        return c[:, 0] * 0.5
    return c.topk(2, dim=1).values.mean(1)


def _encoder(cfg: ModelConfig) -> Encoder2D:
    """The shared 2D encoder of both networks, as the config describes it."""
    return Encoder2D(
        cfg.encoder_channels, cfg.encoder_convs, cfg.encoder_pools, cfg.feature_channels, cfg.norm
    )


class VoxelPoseNet(nn.Module):
    """The multi-view voxel network (see the module docstring).

    ``forward(batch)`` takes a collated batch (:func:`freipose.nn.data.collate_prepared`):
    ``images`` (B, V, 3, S, S), ``K``/``R``/``t``/``dist`` crop cameras, ``view_mask`` (B, V),
    ``center`` (B, 3), optional ``grid_rotation`` (B, 3, 3) (orientation of the voxel grid axes in
    the world, a training augmentation; identity when absent), and returns ``P0`` (B, K, 3),
    ``P0_aux`` (list of (B, K, 3) deep-supervision decodings), ``P1`` (B, K, 3), ``points2d`` (B, V,
    K, 2) refined crop pixels, ``confidence2d`` (B, V, K), ``confidence`` (B, K), ``confidence0``
    (B, K) (peak mass of the score volume) and ``volume_probs`` (B, K, G**3) (the final score
    volume's softmax, for the volumetric loss).
    """

    def __init__(self, cfg: ModelConfig, num_keypoints: int):
        super().__init__()
        self.cfg = cfg
        self.num_keypoints = num_keypoints
        self.encoder = _encoder(cfg)
        self.unet = UNet3D(
            cfg.feature_channels, cfg.unet_channels, num_keypoints, cfg.norm, cfg.deep_supervision
        )
        # optional finer features for the unprojection (model.unproject_levels)
        self.lift = (
            FeatureDecoder(
                cfg.feature_channels, self.encoder.skip_channels, cfg.norm, cfg.unproject_levels
            )
            if cfg.unproject_levels
            else None
        )
        self.refine = (
            Head2D(
                cfg.feature_channels,
                self.encoder.skip_channels,
                num_keypoints,
                cfg.refine_channels,
                cfg.norm,
                heat_in=num_keypoints,
                levels=cfg.head_levels,
            )
            if cfg.refine
            else None
        )
        # log of the weight of P0 in the P1 fusion, per keypoint, relative to the views' total
        # confidence (the refinement helps some keypoints more than others; only with the
        # refinement: an unused parameter would break DDP's gradient reduction). It learns
        # FUSION_LR_SCALE times faster than the network (optimizer_groups).
        self.prior_log_weight = nn.Parameter(torch.zeros(num_keypoints)) if cfg.refine else None

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # checkpoints of version 2 up to 2026-11-22 hold one weight for all keypoints
        key = prefix + "prior_log_weight"
        if self.prior_log_weight is not None and key in state_dict and state_dict[key].ndim == 0:
            state_dict[key] = state_dict[key].expand(self.num_keypoints).clone()
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def forward(self, batch: Mapping[str, Any]) -> dict[str, Any]:
        cfg = self.cfg
        images = batch["images"]
        B, V = images.shape[:2]
        K, R, t, dist = batch["K"], batch["R"], batch["t"], batch["dist"]
        mask, center = batch["view_mask"], batch["center"]
        feats, skip = self.encoder(images.reshape(B * V, *images.shape[2:]))
        h = feats.shape[-1]
        G = cfg.grid_size
        offs = voxel_offsets(G, cfg.cube_size, device=center.device)[None]  # (1, G^3, 3)
        rot = batch.get("grid_rotation")
        if rot is not None:
            offs = offs @ rot.float().transpose(1, 2)  # (B, G^3, 3) world offsets
        points = center[:, None, :] + offs
        vfeats = feats if self.lift is None else self.lift(feats, skip)
        vol, _ = unproject(
            vfeats.float().reshape(B, V, *vfeats.shape[1:]),
            K,
            R,
            t,
            dist,
            mask,
            points,
            cfg.crop_size,
        )
        vol = vol.reshape(B, -1, G, G, G).to(vfeats.dtype)
        scores = self.unet(vol)
        decoded = [softargmax3d(s, center, cfg.cube_size, rot) for s in scores]
        P0, probs = decoded[-1]
        out: dict[str, Any] = {
            "P0": P0,
            "P0_aux": [d[0] for d in decoded[:-1]],
            "confidence0": volume_confidence(probs, G),
            "volume_probs": probs,
        }
        if self.refine is None:
            uv0, _ = project_affine(P0.detach(), K, R, t, dist)
            out.update(
                P1=P0,
                points2d=uv0,
                confidence2d=out["confidence0"][:, None].expand(B, V, -1),
                confidence=out["confidence0"],
            )
            return out
        P0d = P0.detach()
        jitter = batch.get("p0_jitter")
        if jitter is not None and self.training:
            # train the refinement on displaced P0 so it learns to correct P0 rather than
            # to trust it (on the training set P0 is nearly exact)
            P0d = P0d + jitter.to(P0d.dtype)
        uv0, _ = project_affine(P0d, K, R, t, dist)  # (B, V, K, 2)
        heat = gaussian_heatmaps(uv0.reshape(B * V, -1, 2), h, cfg.stride, cfg.heatmap_sigma)
        maps, conf_logits = self.refine(feats, skip, heat)
        # Residual formulation: the map logits are added to a Gaussian log-prior around the
        # projected P0, so an untrained head returns P0's projection (P1 = P0) and training
        # learns corrections.
        # The prior's width is heatmap_sigma * stride crop pixels, whatever the map resolution.
        ms = cfg.map_stride
        prior = gaussian_log_prior(
            uv0.reshape(B * V, -1, 2), maps.shape[-1], ms, cfg.heatmap_sigma * cfg.stride / ms
        )
        logits = maps.float() + prior
        uv, conf = decode_head(logits, conf_logits, ms)
        uv = uv.reshape(B, V, -1, 2)
        conf = conf.reshape(B, V, -1) * mask[:, :, None]
        # P0 enters the fusion as a prior whose weight is a learnt multiple of the views'
        # total confidence, so P1 blends the refined views with P0 as far as they agree
        # (the prior is the unjittered P0: the weight learns how far to trust P0 as it is at
        # inference, while the head learns corrections from the jittered one)
        prior_w = self.prior_log_weight.exp()[None] * conf.sum(1)  # (B, K)
        P1 = triangulate_with_prior(uv, conf, K, R, t, dist, P0.detach(), prior_w + 1e-3)
        out.update(
            P1=P1,
            points2d=uv,
            confidence2d=conf,
            confidence=top2_mean(conf, mask),
            map_logits=logits.reshape(B, V, *logits.shape[1:]),
        )
        return out


class BaselineNet(nn.Module):
    """Per-view 2D keypoints from the same encoder and 2D head (no 3D reasoning).

    ``forward(batch)`` returns ``points2d`` (B, V, K, 2) crop pixels and ``confidence2d``
    (B, V, K); 3D points come from :func:`triangulate_baseline`.
    """

    def __init__(self, cfg: ModelConfig, num_keypoints: int):
        super().__init__()
        self.cfg = cfg
        self.num_keypoints = num_keypoints
        self.encoder = _encoder(cfg)
        self.head = Head2D(
            cfg.feature_channels,
            self.encoder.skip_channels,
            num_keypoints,
            cfg.refine_channels,
            cfg.norm,
            heat_in=0,
            levels=cfg.head_levels,
        )

    def forward(self, batch: Mapping[str, Any]) -> dict[str, Any]:
        images = batch["images"]
        B, V = images.shape[:2]
        feats, skip = self.encoder(images.reshape(B * V, *images.shape[2:]))
        maps, conf_logits = self.head(feats, skip)
        uv, conf = decode_head(maps, conf_logits, self.cfg.map_stride)
        conf = conf.reshape(B, V, -1) * batch["view_mask"][:, :, None]
        return {
            "points2d": uv.reshape(B, V, -1, 2),
            "confidence2d": conf,
            "map_logits": maps.reshape(B, V, *maps.shape[1:]),
        }


def optimizer_groups(model: nn.Module) -> list[dict[str, Any]]:
    """Adam parameter groups: the network, and the P1 fusion weights (``prior_log_weight``)
    whose learning rate is ``FUSION_LR_SCALE`` times the schedule's (``lr_scale``): they are
    a few scalars that only the P1 loss moves, and the refinement trains for part of the run.
    """
    fusion = [p for n, p in model.named_parameters() if n.endswith("prior_log_weight")]
    ids = {id(p) for p in fusion}
    rest = [p for p in model.parameters() if id(p) not in ids]
    groups: list[dict[str, Any]] = [{"params": rest, "lr_scale": 1.0}]
    if fusion:
        groups.append({"params": fusion, "lr_scale": FUSION_LR_SCALE})
    return groups


def build_model(cfg: ModelConfig, num_keypoints: int) -> nn.Module:
    """The network for ``cfg.kind`` (``voxel`` or ``baseline``), pretrained encoder loaded."""
    model: nn.Module
    model = (
        VoxelPoseNet(cfg, num_keypoints) if cfg.kind == "voxel" else BaselineNet(cfg, num_keypoints)
    )
    if cfg.pretrained:
        path = Path(cfg.pretrained)
        if not path.is_file():
            raise FileNotFoundError(f"model.pretrained: encoder weights file not found: {path}")
        state = torch.load(path, map_location="cpu", weights_only=True)
        if isinstance(state, Mapping) and "model" in state:
            state = {
                k[len("encoder.") :]: v
                for k, v in state["model"].items()
                if k.startswith("encoder.")
            }
        res = model.encoder.load_state_dict(state, strict=False)
        log.info(
            "loaded encoder weights from %s (missing %d, unexpected %d keys)",
            path,
            len(res.missing_keys),
            len(res.unexpected_keys),
        )
    return model


def crop_to_image(points2d: np.ndarray, affine: np.ndarray) -> np.ndarray:
    """Map crop pixels (..., V, K, 2) back to full-image pixels with affines (..., V, 3, 3)."""
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
        points2d: (V, K, 2) full-image pixels; confidence2d (V, K).
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


# -- checkpoints -----------------------------------------------------------------------


def state_hash(state: Mapping[str, torch.Tensor]) -> str:
    """SHA-256 over the names, shapes and bytes of a state dict (sorted by name)."""
    h = hashlib.sha256()
    for name in sorted(state):
        v = state[name]
        h.update(name.encode())
        if isinstance(v, torch.Tensor):
            a = v.detach().cpu().contiguous()
            h.update(str(tuple(a.shape)).encode() + str(a.dtype).encode())
            h.update(a.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read and verify a checkpoint written by ``freipose train`` (see docs/formats.md).

    Raises:
        FileNotFoundError: no such file.
        CheckpointError: not a FreiPose pose checkpoint, or the weights fail the hash check.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means a bad file
        raise CheckpointError(
            f"{path}: not a readable checkpoint ({exc}); is it truncated?"
        ) from exc
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(
            f"{path}: not a FreiPose pose checkpoint (expected format {CHECKPOINT_FORMAT!r}); "
            "pass a file written by `freipose train`"
        )
    if ckpt.get("version", 0) > CHECKPOINT_VERSION:
        raise CheckpointError(
            f"{path}: checkpoint version {ckpt.get('version')} is newer than this FreiPose "
            f"supports ({CHECKPOINT_VERSION}); upgrade freipose"
        )
    if ckpt.get("version", 0) < CHECKPOINT_VERSION:
        raise CheckpointError(
            f"{path}: checkpoint version {ckpt.get('version')} was written by an older FreiPose "
            f"whose 2D heads differ from this version's ({CHECKPOINT_VERSION}); retrain it with "
            "`freipose train`"
        )
    if state_hash(ckpt["model"]) != ckpt.get("weights_sha256"):
        raise CheckpointError(f"{path}: the weights do not match their stored hash (corrupt file)")
    return ckpt


def serialize_checkpoint(ckpt: dict[str, Any]) -> bytes:
    """Checkpoint dict to bytes (``torch.save``)."""
    buf = io.BytesIO()
    torch.save(ckpt, buf)
    return buf.getvalue()


def load_checkpoint(
    path: str | Path, device: str | torch.device = "cpu"
) -> tuple[nn.Module, TrainConfig, Any]:
    """Load a trained network for inference.

    Returns:
        ``(model, config, skeleton)``: the network in eval mode on ``device``, its
        :class:`TrainConfig` and :class:`freipose.skeleton.Skeleton`.
    """
    from freipose.skeleton import skeleton_from_dict

    ckpt = read_checkpoint(path)
    config = config_from_dict(ckpt["config"])
    skeleton = skeleton_from_dict(ckpt["skeleton"], f"{path}:skeleton")
    model = build_model(dataclasses.replace(config.model, pretrained=""), len(skeleton.keypoints))
    model.load_state_dict(ckpt["model"])
    model.to(device).eval()
    return model, config, skeleton


# -- prediction ------------------------------------------------------------------------


@torch.no_grad()
def predict_prepared(
    model: nn.Module, batch: dict[str, Any], min_confidence: float = 0.1
) -> dict[str, np.ndarray]:
    """Run a model on a collated batch; outputs in world mm and full-image pixels.

    Returns numpy arrays ``P0``, ``P1`` (B, K, 3), ``confidence`` (B, K), ``points2d``
    (B, V, K, 2) full-image pixels, ``confidence2d`` (B, V, K) (NaN / 0 on padding views).
    """
    from freipose.nn.data import to_device

    device = next(model.parameters()).device
    b = to_device(batch, device)
    use_amp = device.type == "cuda"
    with torch.autocast(device_type=device.type, dtype=torch.bfloat16, enabled=use_amp):
        out = model(b)
    mask = batch["view_mask"].numpy()
    aff = batch["affine"].numpy().astype(np.float64)
    uv = crop_to_image(out["points2d"].float().cpu().numpy().astype(np.float64), aff)
    uv[~mask] = np.nan
    c2 = out["confidence2d"].float().cpu().numpy()
    c2 = np.where(mask[..., None], c2, 0.0)
    if isinstance(getattr(model, "module", model), BaselineNet):
        Ps, cs = [], []
        for i, rig in enumerate(batch["rigs"]):
            n = len(rig)
            X, c = triangulate_baseline(uv[i, :n], c2[i, :n], rig, min_confidence)
            Ps.append(X)
            cs.append(c)
        P = np.stack(Ps)
        return {
            "P0": P,
            "P1": P.copy(),
            "confidence": np.stack(cs),
            "points2d": uv,
            "confidence2d": c2,
        }
    return {
        "P0": out["P0"].float().cpu().numpy().astype(np.float64),
        "P1": out["P1"].float().cpu().numpy().astype(np.float64),
        "confidence": out["confidence"].float().cpu().numpy(),
        "points2d": uv,
        "confidence2d": c2,
    }


def predict_batch(
    model: nn.Module,
    images: Sequence[Sequence[np.ndarray]],
    rigs: Sequence[CameraRig],
    centers: np.ndarray,
) -> dict[str, np.ndarray]:
    """Predict poses from full frames and cube centres (e.g. from the detector).

    Args:
        model: from :func:`load_checkpoint` (voxel network or baseline).
        images: per sample, one BGR uint8 (H, W, 3) full frame per camera of its rig.
        rigs: per sample, the cameras (samples may have different rigs / view counts).
        centers: (B, 3) cube centres in mm; a NaN row gives NaN outputs for that sample.

    Returns:
        ``P0``, ``P1`` (B, K, 3) world mm, ``confidence`` (B, K) in [0, 1], ``points2d``
        (B, Vmax, K, 2) refined full-image pixels (NaN on padding views), ``confidence2d``
        (B, Vmax, K).
    """
    from freipose.nn.data import collate_prepared, prepare_sample

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
    res = {
        "P0": np.full((B, nk, 3), np.nan),
        "P1": np.full((B, nk, 3), np.nan),
        "confidence": np.zeros((B, nk)),
        "points2d": np.full((B, vmax, nk, 2), np.nan),
        "confidence2d": np.zeros((B, vmax, nk)),
    }
    ok = [i for i in range(B) if np.all(np.isfinite(centers[i]))]
    if not ok:
        return res
    items = [
        prepare_sample(
            {"rig": rigs[i], "images": list(images[i]), "index": i}, cfg, center=centers[i]
        )
        for i in ok
    ]
    model.eval()
    out = predict_prepared(model, collate_prepared(items))
    v = out["points2d"].shape[1]
    for key in ("P0", "P1", "confidence"):
        res[key][ok] = out[key]
    res["points2d"][ok, :v] = out["points2d"]
    res["confidence2d"][ok, :v] = out["confidence2d"]
    return res
