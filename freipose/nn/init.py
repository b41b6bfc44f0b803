"""The starting weights of a new training run (``[model] init``): a base, scratch or a file.

``init = "base"`` (the default) starts from the base model that :mod:`freipose.models`
ships for the run's network kind and architecture (the settings of :data:`ARCH_KEYS`,
which fix the weights' shapes; crop size, grid, cube and sigmas may differ); when none is
shipped the run starts from scratch and says so in a warning, so that every architecture
keeps training as before. ``init = "scratch"`` is the random initialisation, and a path
starts from that pose checkpoint, which must be of the same kind and architecture.

A base or checkpoint of another skeleton (other keypoint names or order) gives every weight
except the keypoint-specific ones (the tensors whose shape depends on the number of
keypoints: the 3D U-Net's and the 2D heads' output layers, the heat-map input of the
refinement, the fusion weights), which keep their fresh initialisation; the log says which.
The number and placement of cameras do not enter the weights.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from freipose.errors import FreiPoseError
from freipose.models import base_file, find_base, shipped_bases
from freipose.nn.checkpoint import read_checkpoint
from freipose.nn.config import ModelConfig
from freipose.nn.model import build_model
from freipose.skeleton import Skeleton

log = logging.getLogger(__name__)

#: the ``[model]`` settings that fix the shapes of the weights (a base must agree on them)
ARCH_KEYS = (
    "kind",
    "encoder_channels",
    "encoder_convs",
    "encoder_pools",
    "feature_channels",
    "norm",
    "unet_channels",
    "deep_supervision",
    "refine",
    "refine_channels",
    "head_levels",
    "unproject_levels",
)


class InitError(FreiPoseError):
    """``model.init`` names a checkpoint that cannot initialise this network."""


@dataclass(frozen=True)
class InitResult:
    """Where a run's starting weights came from.

    Attributes:
        source: ``"scratch"``, ``"base:<name>"`` or the checkpoint's path.
        loaded: tensors taken from the source.
        fresh: names of the tensors left at their random initialisation.
    """

    source: str
    loaded: int = 0
    fresh: tuple[str, ...] = ()


def architecture(cfg: ModelConfig) -> dict[str, Any]:
    """The ``[model]`` table of ``cfg`` as a base's manifest stores it (lists for tuples)."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(cfg).items()}


def keypoint_tensors(cfg: ModelConfig, num_keypoints: int) -> frozenset[str]:
    """The names of the weights whose shape depends on the number of keypoints.

    Args:
        cfg: the architecture.
        num_keypoints: K.

    Returns:
        The state-dict names (built on the meta device: no memory, no random numbers).
    """
    with torch.device("meta"):
        a = build_model(_bare(cfg), num_keypoints).state_dict()
        b = build_model(_bare(cfg), num_keypoints + 1).state_dict()
    return frozenset(n for n in a if a[n].shape != b[n].shape)


def _bare(cfg: ModelConfig) -> ModelConfig:
    """``cfg`` without encoder weights to load."""
    from dataclasses import replace

    return replace(cfg, pretrained="")


def _differences(stored: Mapping[str, Any], cfg: ModelConfig) -> list[str]:
    """The :data:`ARCH_KEYS` on which a stored ``[model]`` table and ``cfg`` disagree."""
    mine = architecture(cfg)

    def norm(v: Any) -> Any:
        return list(v) if isinstance(v, (list, tuple)) else v

    return [k for k in ARCH_KEYS if norm(stored.get(k, mine[k])) != norm(mine[k])]


def _load(
    model: nn.Module, ckpt: Mapping[str, Any], cfg: ModelConfig, skeleton: Skeleton, source: str
) -> InitResult:
    """Copy the weights of ``ckpt`` into ``model``.

    All but the keypoint-specific ones when the skeletons differ.
    """
    theirs = tuple(ckpt["skeleton"]["keypoints"])
    same = theirs == tuple(skeleton.keypoints)
    drop = frozenset() if same else keypoint_tensors(cfg, len(skeleton.keypoints))
    own = model.state_dict()
    stored = ckpt["model"]
    take = {
        n: v
        for n, v in stored.items()
        if n in own and n not in drop and tuple(v.shape) == tuple(own[n].shape)
    }
    fresh = tuple(sorted(set(own) - set(take)))
    own.update(take)
    model.load_state_dict(own)
    if not same:
        log.info(
            "%s was trained on another skeleton (%d keypoints: %s; this run: %d: %s): every "
            "weight is taken except the keypoint-specific output layers, which start fresh (%s)",
            source, len(theirs), ", ".join(theirs[:4]) + (", ..." if len(theirs) > 4 else ""),
            len(skeleton.keypoints), ", ".join(skeleton.keypoints[:4])
            + (", ..." if len(skeleton.keypoints) > 4 else ""), ", ".join(fresh),
        )  # fmt: skip
    elif fresh:
        log.info("%s: %d tensors start fresh (%s)", source, len(fresh), ", ".join(fresh))
    return InitResult(source, len(take), fresh)


def initialize(model: nn.Module, cfg: ModelConfig, skeleton: Skeleton) -> InitResult:
    """Give a newly built network the starting weights that ``cfg.init`` names.

    Args:
        model: the network of ``cfg`` for ``skeleton`` (from :func:`build_model`).
        cfg: its architecture; ``cfg.init`` is ``"base"``, ``"scratch"`` or a path.
        skeleton: the keypoints the run trains.

    Returns:
        Where the weights came from.

    Raises:
        InputFileError: ``cfg.init`` names a file that does not exist.
        CheckpointError: the file is damaged or not a pose checkpoint.
        InitError: the checkpoint is of another network kind or architecture.
    """
    if cfg.init == "scratch":
        return InitResult("scratch")
    if cfg.init == "base":
        if cfg.pretrained:
            log.info("model.pretrained names encoder weights: not starting from a base model")
            return InitResult("scratch")
        return _from_base(model, cfg, skeleton)
    path = Path(cfg.init)
    ckpt = read_checkpoint(path, "model.init")
    stored = ckpt["config"]["model"]
    diff = _differences(stored, cfg)
    if diff:
        raise InitError(
            f"model.init: {path} is a network of another architecture ("
            + ", ".join(f"{k} {stored.get(k)!r} there, {getattr(cfg, k)!r} here" for k in diff)
            + '); set the same [model] settings, or model.init = "scratch"'
        )
    res = _load(model, ckpt, cfg, skeleton, str(path))
    log.info("starting from %s (step %s): %d tensors", path, ckpt.get("step"), res.loaded)
    return res


def _from_base(model: nn.Module, cfg: ModelConfig, skeleton: Skeleton) -> InitResult:
    """Load the shipped base of ``cfg``'s architecture, or warn and keep the fresh weights."""
    base = find_base(cfg.kind, architecture(cfg), ARCH_KEYS)
    if base is None:
        have = ", ".join(f"{b.name} ({b.kind})" for b in shipped_bases()) or "none"
        log.warning(
            'model.init = "base": no base model is shipped for this %s architecture (shipped: '
            '%s; they fit [model] preset = "small" without changes to its layers); training '
            'starts from scratch (set model.init = "scratch" to silence this)',
            cfg.kind, have,
        )  # fmt: skip
        return InitResult("scratch")
    with base_file(base) as path:
        ckpt = read_checkpoint(path, "model.init")
    res = _load(model, ckpt, cfg, skeleton, f"base model {base.name!r}")
    log.info(
        "starting from the base model %r (%s, %d steps on synthetic sessions): %d tensors",
        base.name, base.file, base.steps, res.loaded,
    )  # fmt: skip
    return InitResult(f"base:{base.name}", res.loaded, res.fresh)
