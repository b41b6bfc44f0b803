"""Losses on unlabeled instants, and their place in a training step.

Every term is a robust distance ``s * log(1 + e / s)`` (``s`` = ``unlabeled.robust_scale``):
like the labeled losses' Euclidean distance for small errors ``e``, growing only
logarithmically for large ones, so real fast movements, occlusions and the network's own
gross mistakes do not dominate. 3D errors are in voxels (mm / voxel size), 2D errors in
feature pixels (crop px / stride), as in :mod:`freipose.nn.losses`. The targets of the
consistency terms (the fused P1, the unaugmented instant, the teacher) are detached:
the network is pulled toward its own consensus, the consensus is not pulled away from
the data.

* :func:`multiview_loss`: each view's refined 2D point against the projection of P1,
  weighted by the view's confidence, views that cannot see the point (padding, point
  behind the camera or outside the crop) left out;
* :func:`p0p1_loss`: P0 against P1;
* :func:`temporal_loss`: the acceleration of the pose along each clip;
* :func:`equivariance_loss`: the pose of an instant under another augmentation and view
  subset against the pose of the first;
* :func:`bone_loss`: distances between nearly rigid keypoint pairs outside two standard
  deviations of the labeled set's (:func:`rigid_pairs`);
* :func:`teacher_loss`: the pose against the P1 of a teacher network (an exponential moving
  average of the trained one) where the teacher's views agree.

:class:`UnlabeledTraining` draws the step's clips, runs the network on them and adds the
weighted terms to the labeled loss.
"""

from __future__ import annotations

import copy
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from freipose.io.labels import LabelSet
from freipose.nn.config import ModelConfig, TrainConfig
from freipose.nn.config_unlabeled import UnlabeledConfig
from freipose.nn.data import to_device
from freipose.nn.geometry import project_affine
from freipose.nn.unlabeled import (
    UnlabeledBatch,
    UnlabeledClips,
    UnlabeledDataError,
    open_unlabeled,
)


def robust(err: torch.Tensor, scale: float) -> torch.Tensor:
    """``scale * log(1 + err / scale)`` of non-negative errors (same shape)."""
    return scale * torch.log1p(err / scale)


def _norm(d: torch.Tensor) -> torch.Tensor:
    """Euclidean norm over the last axis, differentiable at 0."""
    return torch.sqrt((d.float() ** 2).sum(-1) + 1e-6)


def _weighted_mean(err: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Per-sample weighted mean over every axis but the first, then mean over samples."""
    w = weight.to(err.dtype)
    dims = tuple(range(1, err.ndim))
    return ((err * w).sum(dims) / w.sum(dims).clamp_min(1e-6)).mean()


def view_residuals(
    out: Mapping[str, Any], batch: Mapping[str, Any], model: ModelConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """Distances of the views' refined points from the projections of the (detached) P1.

    Args:
        out: the network output (``P1``, ``points2d``).
        batch: the collated batch (crop cameras, ``view_mask``).
        model: gives the crop size and the stride.

    Returns:
        ``(err, sees)``: (B, V, K) distances in feature pixels and (B, V, K) bool, the
        views that can see the point (real view, point in front of it and inside its crop).
    """
    uv, front = project_affine(
        out["P1"].detach().float(), batch["K"], batch["R"], batch["t"], batch["dist"]
    )
    S = model.crop_size
    inside = (uv >= -0.5).all(-1) & (uv <= S - 0.5).all(-1)
    sees = front & inside & batch["view_mask"][:, :, None]
    err = _norm(out["points2d"] - uv) / model.stride
    return err, sees


def multiview_loss(
    out: Mapping[str, Any], batch: Mapping[str, Any], model: ModelConfig, scale: float
) -> torch.Tensor:
    """Refined 2D points against the projections of the fused P1 (confidence-weighted)."""
    err, sees = view_residuals(out, batch, model)
    w = out["confidence2d"].detach().float() * sees
    return _weighted_mean(robust(err, scale), w)


def p0p1_loss(out: Mapping[str, Any], model: ModelConfig, scale: float) -> torch.Tensor:
    """P0 against the (detached) P1, in voxels."""
    e = _norm(out["P0"] - out["P1"].detach()) / model.voxel_size
    return robust(e, scale).mean()


def temporal_loss(
    poses: torch.Tensor, clips: int, frames: int, model: ModelConfig, scale: float
) -> torch.Tensor:
    """Robust norm of the acceleration along the clips (voxels per frame^2).

    Args:
        poses: (N, K, 3) with N >= clips * frames; instant ``c * frames + f`` is frame ``f``
            of clip ``c``.
        clips: clips.
        frames: instants per clip (below 3: no acceleration, 0).
        model: gives the voxel size.
        scale: the robust scale.
    """
    if frames < 3:
        return poses.new_zeros(())
    P = poses[: clips * frames].float().reshape(clips, frames, *poses.shape[1:])
    acc = P[:, 2:] - 2 * P[:, 1:-1] + P[:, :-2]
    return robust(_norm(acc) / model.voxel_size, scale).mean()


def equivariance_loss(
    poses: torch.Tensor, ub: UnlabeledBatch, model: ModelConfig, scale: float
) -> torch.Tensor:
    """The clips' middle instants under the second augmentation against the first (detached)."""
    n, F = ub.clips, ub.clip_frames
    first = poses[torch.arange(n, device=poses.device) * F + ub.middle].detach()
    again = poses[n * F : n * F + n]
    return robust(_norm(again - first) / model.voxel_size, scale).mean()


@dataclass(frozen=True)
class RigidPairs:
    """Keypoint pairs whose distance varies little in the labeled set.

    Attributes:
        pairs: (P, 2) keypoint indices.
        mean: (P,) mean distance (mm).
        std: (P,) standard deviation of the distance (mm).
    """

    pairs: np.ndarray
    mean: np.ndarray
    std: np.ndarray


def rigid_pairs(points3d: np.ndarray, max_cv: float = 0.2, min_count: int = 5) -> RigidPairs:
    """The nearly rigid keypoint pairs of the labels (at most 2 per keypoint).

    Args:
        points3d: (N, K, 3) labels (mm), NaN where unlabeled.
        max_cv: largest coefficient of variation (std / mean) of a pair's distance.
        min_count: fewest instants that label both keypoints of a pair.

    Returns:
        The pairs, most rigid first; none when the labels show none.
    """
    p = np.asarray(points3d, np.float64)
    K = p.shape[1]
    rows = []
    for i in range(K):
        for j in range(i + 1, K):
            d = np.linalg.norm(p[:, i] - p[:, j], axis=-1)
            d = d[np.isfinite(d)]
            if len(d) >= min_count and d.mean() > 0:
                rows.append((d.std() / d.mean(), i, j, d.mean(), d.std()))
    rows.sort()
    used = np.zeros(K, int)
    keep = []
    for cv, i, j, m, s in rows:
        if cv <= max_cv and used[i] < 2 and used[j] < 2:
            keep.append((i, j, m, s))
            used[i] += 1
            used[j] += 1
    if not keep:
        return RigidPairs(np.zeros((0, 2), np.int64), np.zeros(0), np.zeros(0))
    a = np.asarray(keep)
    return RigidPairs(a[:, :2].astype(np.int64), a[:, 2], a[:, 3])


def bone_loss(
    poses: torch.Tensor, bones: RigidPairs, model: ModelConfig, scale: float
) -> torch.Tensor:
    """Rigid-pair distances beyond two standard deviations of the labels' (voxels)."""
    if not len(bones.pairs):
        return poses.new_zeros(())
    ij = torch.as_tensor(bones.pairs, device=poses.device)
    length = _norm(poses[:, ij[:, 0]] - poses[:, ij[:, 1]])
    mean = torch.as_tensor(bones.mean, dtype=length.dtype, device=poses.device)
    std = torch.as_tensor(bones.std, dtype=length.dtype, device=poses.device)
    excess = torch.relu((length - mean).abs() - 2 * std) / model.voxel_size
    return robust(excess, scale).mean()


def agreeing(
    out: Mapping[str, Any], batch: Mapping[str, Any], model: ModelConfig, limit: float
) -> torch.Tensor:
    """(B, K) bool: keypoints whose seeing views agree with P1 within ``limit`` feature px.

    The agreement is the confidence-weighted RMS distance of the views' refined points from
    the projections of P1 (:func:`view_residuals`); at least two views must see the point.
    """
    err, sees = view_residuals(out, batch, model)
    w = out["confidence2d"].float() * sees
    rms = torch.sqrt((w * err**2).sum(1) / w.sum(1).clamp_min(1e-6))
    return (rms < limit) & (sees.sum(1) >= 2)


def teacher_loss(
    poses: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, model: ModelConfig,
    scale: float,
) -> torch.Tensor:  # fmt: skip
    """Poses (N, K, 3) against the teacher's (N, K, 3) where ``mask`` (N, K) (voxels)."""
    e = robust(_norm(poses - target) / model.voxel_size, scale)
    return _weighted_mean(e, mask.float())


_REFINED = ("u_multiview", "u_p0p1")  # the terms that act through the refined points


class UnlabeledTraining:
    """The unlabeled part of every training step.

    Args:
        clips: the step's unlabeled clips.
        config: the ``[unlabeled]`` table.
        model: the architecture.
        bones: the labels' rigid pairs (:func:`rigid_pairs`).
        steps: the run's steps (``config.start`` is a fraction of them).
        refine_from: the first step that trains the refinement head
            (``schedule.refine_start``); before it ``multiview`` and ``p0p1``, which act
            through the refined points, are weighted 0 (they are still logged).
    """

    def __init__(
        self,
        clips: UnlabeledClips,
        config: UnlabeledConfig,
        model: ModelConfig,
        bones: RigidPairs,
        steps: int,
        refine_from: int = 0,
    ):
        self.clips, self.config, self.model, self.bones = clips, config, model, bones
        self.first_step = int(round(config.start * steps))
        self.refine_from = int(refine_from)
        self.teacher: torch.nn.Module | None = None

    def active(self, step: int) -> bool:
        """Whether the unlabeled losses act at ``step``."""
        return step >= self.first_step

    def loss(
        self, net: torch.nn.Module, step: int, device: torch.device, amp: bool
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """The weighted unlabeled terms of ``step`` (the network in training mode).

        Returns:
            ``(total, parts)``: the weighted sum and the terms (``u_multiview``, ``u_p0p1``,
            ``u_temporal``, ``u_equivariance``, ``u_bones``, ``u_teacher``).
        """
        cfg, mcfg, s = self.config, self.model, self.config.robust_scale
        ub = self.clips.batch(step)
        b = to_device(ub.batch, device)
        with torch.autocast(device_type=device.type, dtype=torch.bfloat16, enabled=amp):
            out = net(b)
        parts: dict[str, torch.Tensor] = {
            "u_multiview": multiview_loss(out, b, mcfg, s),
            "u_p0p1": p0p1_loss(out, mcfg, s),
        }
        parts["u_temporal"] = sum(
            temporal_loss(out[k], ub.clips, ub.clip_frames, mcfg, s) for k in ("P0", "P1")
        )
        parts["u_equivariance"] = sum(equivariance_loss(out[k], ub, mcfg, s) for k in ("P0", "P1"))
        parts["u_bones"] = sum(bone_loss(out[k], self.bones, mcfg, s) for k in ("P0", "P1"))
        refined = step >= self.refine_from
        total = sum(
            getattr(cfg, "weight_" + k[2:]) * v * (refined or k not in _REFINED)
            for k, v in parts.items()
        )
        if cfg.weight_teacher > 0:
            target, mask = self._pseudo_labels(net, b, amp)
            parts["u_teacher"] = sum(
                teacher_loss(out[k], target, mask, mcfg, s) for k in ("P0", "P1")
            )
            total = total + cfg.weight_teacher * parts["u_teacher"]
        return total, {k: float(v.detach()) for k, v in parts.items()}

    @torch.no_grad()
    def _pseudo_labels(
        self, net: torch.nn.Module, b: Mapping[str, Any], amp: bool
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The teacher's P1 (N, K, 3) and where its views agree (N, K)."""
        if self.teacher is None:
            self.teacher = copy.deepcopy(getattr(net, "module", net)).eval()
        dev = b["images"].device
        with torch.autocast(device_type=dev.type, dtype=torch.bfloat16, enabled=amp):
            t_out = self.teacher(b)
        mask = agreeing(t_out, b, self.model, self.config.teacher_agreement)
        return t_out["P1"].float(), mask

    @torch.no_grad()
    def after_step(self, model: torch.nn.Module) -> None:
        """Move the teacher toward the trained network (exponential moving average)."""
        if self.teacher is None:
            return
        d = self.config.teacher_decay
        for pt, ps in zip(self.teacher.parameters(), model.parameters()):
            pt.mul_(d).add_(ps.detach(), alpha=1 - d)
        for bt, bs in zip(self.teacher.buffers(), model.buffers()):
            bt.copy_(bs)

    def close(self) -> None:
        """Release the videos."""
        self.clips.close()


def unlabeled_training(
    config: TrainConfig, base: Path, labels: LabelSet, cameras: Sequence[str] | None = None
) -> UnlabeledTraining | None:
    """The unlabeled part of a run's steps, or None without ``[unlabeled] sessions``.

    Args:
        config: the resolved training config.
        base: the folder the ``[unlabeled]`` paths are relative to (the config file's).
        labels: the training labels (cube centres, rigid pairs, the world's up).
        cameras: ``[data] cameras`` (None: every calibrated camera).

    Raises:
        UnlabeledDataError: unusable sessions or centres (see :func:`open_unlabeled`), the
            baseline, or several processes (torchrun).
    """
    unl = config.unlabeled
    if not unl.enabled:
        return None
    if config.model.kind != "voxel":
        raise UnlabeledDataError(
            "the [unlabeled] losses train the voxel network (P0, P1 and the fused views); "
            "remove [unlabeled] sessions to train the baseline"
        )
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        # DistributedDataParallel reduces each parameter's gradient once per backward; the
        # unlabeled clips add a second forward pass before it
        raise UnlabeledDataError(
            "[unlabeled] training runs in one process; start it without torchrun (or remove "
            "[unlabeled] sessions to train on several GPUs)"
        )
    sessions = open_unlabeled(unl, base, labels, cameras)
    aug = config.augment if config.augment.enabled else None
    sched = config.schedule
    clips = UnlabeledClips(
        sessions, unl, config.model, aug, sched.seed, unl.clips_per_step(sched.batch_size)
    )
    refine_from = int(round(sched.refine_start * sched.steps))
    bones = rigid_pairs(labels.points3d)
    return UnlabeledTraining(clips, unl, config.model, bones, sched.steps, refine_from)
