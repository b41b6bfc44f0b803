"""The FreiPose voxel network and the triangulation baseline (the networks only).

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
single view the fusion keeps P0's depth (eq. 5.3). At inference the fusion is repeated
without the views whose refined point lies more than ``model.fusion_reject`` voxels from
P1 (:func:`freipose.nn.layers.refuse_outlier_views`), as the baseline's triangulation
leaves out RANSAC outliers.

:class:`BaselineNet`: the comparison the paper makes (DeepLabCut + triangulation): the same
encoder and 2D head predict every view's keypoints independently; 3D comes from robust
RANSAC triangulation (:func:`freipose.nn.inference.triangulate_baseline`). Checkpoints are
in :mod:`freipose.nn.checkpoint`, batch inference in :mod:`freipose.nn.inference`.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

from freipose.errors import InputFileError
from freipose.io.checkpoints import POSE_NETWORK, UNSAFE, kind_error, kind_of, load_safely
from freipose.nn.config import ModelConfig
from freipose.nn.geometry import pixels_to_normalized, project_affine, voxel_axis, voxel_offsets
from freipose.nn.layers import (
    Encoder2D,
    FeatureDecoder,
    Head2D,
    UNet3D,
    decode_head,
    gaussian_heatmaps,
    gaussian_log_prior,
    refuse_outlier_views,
    softargmax3d,
    triangulate_normalized,
    volume_confidence,
)
from freipose.nn.unprojection import unproject, unproject_gather

log = logging.getLogger(__name__)

FUSION_LR_SCALE = 10.0  # learning-rate multiplier of the P1 fusion weights


def top2_mean(conf: torch.Tensor, view_mask: torch.Tensor) -> torch.Tensor:
    """Per-keypoint confidence from per-view ones: mean of the two most confident views.

    Args:
        conf: (B, V, K) in [0, 1].
        view_mask: (B, V) bool, real views.

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


Dense = Callable[..., Any]


@contextlib.contextmanager
def _dense_precision(device_type: str) -> Iterator[Dense]:
    """Autocast off for a network's forward, except in the dense parts it runs through.

    Inside the context everything (unprojection geometry, soft-argmax, projection,
    triangulation) computes in float32: a bfloat16 matrix product of world coordinates in
    mm rounds them by up to a few mm. The dense parts (convolutions) keep the autocast that
    was active on entry.

    Args:
        device_type: ``cpu`` or ``cuda``.

    Yields:
        ``run(module, *args)``: the module's output, computed under the entry autocast.
    """
    enabled = torch.is_autocast_enabled(device_type)
    dtype = torch.get_autocast_dtype(device_type)

    def run(module: nn.Module, *args: Any) -> Any:
        with torch.autocast(device_type=device_type, dtype=dtype, enabled=enabled):
            return module(*args)

    with torch.autocast(device_type=device_type, enabled=False):
        yield run


def _view_crops(images: torch.Tensor, channels_last: bool) -> torch.Tensor:
    """(B, V, 3, S, S) crops as one (B*V, 3, S, S) batch, channels last when asked."""
    x = images.reshape(images.shape[0] * images.shape[1], *images.shape[2:])
    return x.contiguous(memory_format=torch.channels_last) if channels_last else x


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
        # the optimized backend (freipose.nn.fast): channels-last crops and volumes, the
        # unprojection as one gather; the same poses within fp32 rounding
        self.fast = False
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

    def forward(self, batch: Mapping[str, Any]) -> dict[str, Any]:
        """Poses P0 and P1 of a collated batch (:class:`freipose.nn.types.NetworkOutput`).

        Under autocast only the encoder, the feature lift, the 3D U-Net and the refinement
        head run in reduced precision; the geometry and the decoding stay in float32.
        """
        images = batch["images"]
        B, V = images.shape[:2]
        with _dense_precision(images.device.type) as dense:
            feats, skip = dense(self.encoder, _view_crops(images, self.fast))
            out = self._initial_pose(batch, feats, skip, dense)
            if self.refine is None or self.prior_log_weight is None:
                uv0, _ = project_affine(
                    out["P0"].detach(), batch["K"], batch["R"], batch["t"], batch["dist"]
                )
                out.update(
                    P1=out["P0"],
                    points2d=uv0,
                    confidence2d=out["confidence0"][:, None].expand(B, V, -1),
                    confidence=out["confidence0"],
                )
                return out
            out.update(
                self._refined_pose(
                    batch, feats, skip, out["P0"], self.refine, self.prior_log_weight, dense
                )
            )
        return out

    def _initial_pose(
        self,
        batch: Mapping[str, Any],
        feats: torch.Tensor,
        skip: list[torch.Tensor],
        dense: Dense,
    ) -> dict[str, Any]:
        """P0: the features unprojected into the voxel grid, the 3D U-Net and soft-argmax.

        Args:
            batch: the collated batch.
            feats: (B*V, C, h, w) encoder features.
            skip: the encoder's skip maps.
            dense: runs the lift and the U-Net (:func:`_dense_precision`).

        Returns:
            ``P0``, ``P0_aux``, ``confidence0`` and ``volume_probs``.
        """
        cfg = self.cfg
        B, V = batch["images"].shape[:2]
        center = batch["center"]
        G = cfg.grid_size
        rot = batch.get("grid_rotation")
        vfeats = feats if self.lift is None else dense(self.lift, feats, skip)
        cams = (batch["K"], batch["R"], batch["t"], batch["dist"], batch["view_mask"])
        vfeats5 = vfeats.float().reshape(B, V, *vfeats.shape[1:])
        # the gather's backward (a sort of its plan) costs more than grid_sample's: with a
        # gradient to the features the optimized backend unprojects as the eager one does
        if self.fast and not (vfeats5.requires_grad and torch.is_grad_enabled()):
            axes = torch.eye(3, device=center.device).expand(B, 3, 3) if rot is None else rot
            grid = (center, axes, voxel_axis(G, cfg.cube_size, device=center.device))
            vol, _ = unproject_gather(vfeats5, *cams, grid, cfg.crop_size)
        else:
            offs = voxel_offsets(G, cfg.cube_size, device=center.device)[None]  # (1, G^3, 3)
            if rot is not None:
                offs = offs @ rot.float().transpose(1, 2)  # (B, G^3, 3) world offsets
            vol, _ = unproject(vfeats5, *cams, center[:, None, :] + offs, cfg.crop_size)
        vol = vol.reshape(B, -1, G, G, G).to(vfeats.dtype)
        scores = dense(self.unet, vol)
        decoded = [softargmax3d(s, center, cfg.cube_size, rot) for s in scores]
        P0, probs = decoded[-1]
        return {
            "P0": P0,
            "P0_aux": [d[0] for d in decoded[:-1]],
            "confidence0": volume_confidence(probs, G),
            "volume_probs": probs,
        }

    def _refined_pose(
        self,
        batch: Mapping[str, Any],
        feats: torch.Tensor,
        skip: list[torch.Tensor],
        P0: torch.Tensor,
        refine: Head2D,
        prior_log_weight: torch.Tensor,
        dense: Dense,
    ) -> dict[str, Any]:
        """P1: the 2D refinement of P0's projections fused by confidence-weighted triangulation.

        Args:
            batch: the collated batch.
            feats: (B*V, C, h, w) encoder features.
            skip: the encoder's skip maps.
            P0: (B, K, 3) the initial pose.
            refine: the refinement head.
            prior_log_weight: (K,) log of P0's weight in the fusion.
            dense: runs the refinement head (:func:`_dense_precision`).

        Returns:
            ``P1``, ``points2d``, ``confidence2d``, ``confidence`` and ``map_logits``.
        """
        cfg = self.cfg
        B, V = batch["images"].shape[:2]
        K, R, t, dist = batch["K"], batch["R"], batch["t"], batch["dist"]
        mask = batch["view_mask"]
        h = feats.shape[-1]
        P0d = P0.detach()
        jitter = batch.get("p0_jitter")
        if jitter is not None and self.training:
            # train the refinement on displaced P0 so it learns to correct P0 rather than
            # to trust it (on the training set P0 is nearly exact)
            P0d = P0d + jitter.to(P0d.dtype)
        uv0, _ = project_affine(P0d, K, R, t, dist)  # (B, V, K, 2)
        heat = gaussian_heatmaps(uv0.reshape(B * V, -1, 2), h, cfg.stride, cfg.heatmap_sigma)
        maps, conf_logits = dense(refine, feats, skip, heat)
        # Residual formulation: the map logits are added to a Gaussian log-prior around the
        # projected P0, so an untrained head returns P0's projection (P1 = P0) and training
        # learns corrections.
        # The prior's width is heatmap_sigma * stride crop pixels, whatever the map resolution.
        ms = cfg.map_stride
        prior = gaussian_log_prior(
            uv0.reshape(B * V, -1, 2), maps.shape[-1], ms, cfg.heatmap_sigma * cfg.stride / ms
        )
        logits = maps.float() + prior
        uv, conf = decode_head(logits, conf_logits, ms, 0 if self.training else cfg.map_window)
        uv = uv.reshape(B, V, -1, 2)
        conf = conf.reshape(B, V, -1) * mask[:, :, None]
        # P0 enters the fusion as a prior whose weight is a learnt multiple of the views'
        # total confidence, so P1 blends the refined views with P0 as far as they agree
        # (the prior is the unjittered P0: the weight learns how far to trust P0 as it is at
        # inference, while the head learns corrections from the jittered one)
        prior_w = prior_log_weight.exp()[None] * conf.sum(1)  # (B, K)
        xy = pixels_to_normalized(uv.float(), K.float(), None if dist is None else dist.float())
        P1 = triangulate_normalized(xy, conf, R, t, P0.detach(), prior_w + 1e-3)
        if not self.training and cfg.fusion_reject > 0:
            P1 = refuse_outlier_views(
                P1, uv, conf, (K, R, t, dist), P0.detach(), prior_log_weight.exp()[None],
                cfg.fusion_reject * cfg.voxel_size, xy=xy,
            )  # fmt: skip
        return {
            "P1": P1,
            "points2d": uv,
            "confidence2d": conf,
            "confidence": top2_mean(conf, mask),
            "map_logits": logits.reshape(B, V, *logits.shape[1:]),
        }


class BaselineNet(nn.Module):
    """Per-view 2D keypoints from the same encoder and 2D head (no 3D reasoning).

    ``forward(batch)`` returns ``points2d`` (B, V, K, 2) crop pixels and ``confidence2d``
    (B, V, K); 3D points come from :func:`triangulate_baseline`.
    """

    def __init__(self, cfg: ModelConfig, num_keypoints: int):
        super().__init__()
        self.cfg = cfg
        self.num_keypoints = num_keypoints
        self.fast = False  # channels-last crops (freipose.nn.fast)
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
        """Per-view 2D keypoints of a collated batch (see the class docstring).

        Under autocast only the encoder and the head run in reduced precision.
        """
        images = batch["images"]
        B, V = images.shape[:2]
        with _dense_precision(images.device.type) as dense:
            feats, skip = dense(self.encoder, _view_crops(images, self.fast))
            maps, conf_logits = dense(self.head, feats, skip)
            window = 0 if self.training else self.cfg.map_window
            uv, conf = decode_head(maps, conf_logits, self.cfg.map_stride, window)
            conf = conf.reshape(B, V, -1) * batch["view_mask"][:, :, None]
        return {
            "points2d": uv.reshape(B, V, -1, 2),
            "confidence2d": conf,
            "map_logits": maps.reshape(B, V, *maps.shape[1:]),
        }


def optimizer_groups(model: nn.Module) -> list[dict[str, Any]]:
    """Adam parameter groups: the network, and the P1 fusion weights (``prior_log_weight``).

    The fusion weights' learning rate is ``FUSION_LR_SCALE`` times the schedule's
    (``lr_scale``): they are a few scalars that only the P1 loss moves, and the refinement
    trains for part of the run.

    Args:
        model: a network from :func:`build_model`.

    Returns:
        One or two groups (``params``, ``lr_scale``).
    """
    fusion = [p for n, p in model.named_parameters() if n.endswith("prior_log_weight")]
    ids = {id(p) for p in fusion}
    rest = [p for p in model.parameters() if id(p) not in ids]
    groups: list[dict[str, Any]] = [{"params": rest, "lr_scale": 1.0}]
    if fusion:
        groups.append({"params": fusion, "lr_scale": FUSION_LR_SCALE})
    return groups


def build_model(cfg: ModelConfig, num_keypoints: int) -> nn.Module:
    """The network for ``cfg.kind`` (``voxel`` or ``baseline``), pretrained encoder loaded.

    Args:
        cfg: the architecture.
        num_keypoints: K, keypoints the network predicts.

    Returns:
        A :class:`VoxelPoseNet` or :class:`BaselineNet` (training mode, on the CPU).

    Raises:
        InputFileError: ``cfg.pretrained`` names a file that does not exist.
        CheckpointFileError: ``cfg.pretrained`` names a damaged file, a detector checkpoint
            or a file that is not only tensors (not written by FreiPose or PyTorch).
    """
    model: nn.Module
    model = (
        VoxelPoseNet(cfg, num_keypoints) if cfg.kind == "voxel" else BaselineNet(cfg, num_keypoints)
    )
    if cfg.pretrained:
        path = Path(cfg.pretrained)
        if not path.is_file():
            raise InputFileError(f"model.pretrained: encoder weights file not found: {path}")
        state = load_safely(path)
        kind = kind_of(state)
        if state is UNSAFE or kind.startswith("detector"):
            raise kind_error(path, kind, POSE_NETWORK, "model.pretrained")
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
