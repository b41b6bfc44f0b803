"""Pose checkpoints: writing, reading, verifying and loading them for inference.

A checkpoint is a ``torch.save`` dict (see docs/formats.md) with ``format`` =
:data:`CHECKPOINT_FORMAT` and a ``version``; it is read without running code from it, and a
file of another kind (a detector, not a FreiPose file) is refused by
:func:`freipose.io.checkpoints.read_checkpoint_as` with a message naming the right one.
Each version that can still be read has one loading rule in :data:`LOADING_RULES` that
brings its weights to the layout of :data:`CHECKPOINT_VERSION`:

* version 1: 2D heads with one decoder level and no ``head_levels`` in the config;
  refused (retrain).
* version 2: the current 2D heads; the P1 fusion weight ``prior_log_weight`` is either one
  weight per keypoint or, in the earliest files of this version, a single weight for all
  keypoints, which is expanded to every keypoint.
* version 3: the current layout (one fusion weight per keypoint); loaded as it is.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import random
from collections.abc import Callable, Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
import torch
from torch import nn

from freipose import __version__
from freipose.io.checkpoints import POSE_FORMAT, POSE_NETWORK, CheckpointFileError
from freipose.io.checkpoints import read_checkpoint_as as _read_checkpoint_as
from freipose.nn.config import InferenceOverrides, TrainConfig, config_from_dict, config_to_dict
from freipose.nn.model import build_model
from freipose.skeleton import Skeleton, skeleton_from_dict

CHECKPOINT_FORMAT = POSE_FORMAT
CHECKPOINT_VERSION = 3


class CheckpointError(CheckpointFileError):
    """A checkpoint file is missing, corrupt or of another kind (the message says which)."""


StateDict = dict[str, torch.Tensor]


def _state_v2(state: StateDict, num_keypoints: int) -> StateDict:
    """Version 2: a single fusion weight becomes one weight per keypoint."""
    w = state.get("prior_log_weight")
    if w is not None and w.ndim == 0:
        state = dict(state)
        state["prior_log_weight"] = w.expand(num_keypoints).clone()
    return state


def _state_current(state: StateDict, num_keypoints: int) -> StateDict:
    """Version 3 (current): the weights are used as stored."""
    return state


#: checkpoint version -> function ``(state, num_keypoints) -> state`` in the current layout
LOADING_RULES: Mapping[int, Callable[[StateDict, int], StateDict]] = MappingProxyType(
    {2: _state_v2, CHECKPOINT_VERSION: _state_current}
)


def state_hash(state: Mapping[str, torch.Tensor]) -> str:
    """SHA-256 over the names, shapes and bytes of a state dict (sorted by name).

    Args:
        state: parameter name -> tensor (any shape, dtype and device).

    Returns:
        The hex digest.
    """
    h = hashlib.sha256()
    for name in sorted(state):
        v = state[name]
        h.update(name.encode())
        if isinstance(v, torch.Tensor):
            a = v.detach().cpu().contiguous()
            h.update(str(tuple(a.shape)).encode() + str(a.dtype).encode())
            h.update(a.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def _check_version(path: Path, version: int) -> None:
    """Raise :class:`CheckpointError` for a version without a loading rule."""
    if version > CHECKPOINT_VERSION:
        raise CheckpointError(
            f"{path}: checkpoint version {version} is newer than this FreiPose "
            f"supports ({CHECKPOINT_VERSION}); upgrade freipose"
        )
    if version not in LOADING_RULES:
        raise CheckpointError(
            f"{path}: checkpoint version {version} was written by an older FreiPose "
            f"whose 2D heads differ from this version's ({CHECKPOINT_VERSION}); retrain it with "
            "`freipose train`"
        )


def read_checkpoint(path: str | Path, option: str | None = None) -> dict[str, Any]:
    """Read and verify a checkpoint written by ``freipose train`` (see docs/formats.md).

    The file is read without running code from it and must be of a pose-network kind
    (:func:`freipose.io.checkpoints.checkpoint_kind`). The stored weights are checked
    against their hash and then brought to the current layout by the loading rule of the
    checkpoint's version (:data:`LOADING_RULES`); the other entries are returned as stored.

    Args:
        path: the checkpoint file.
        option: the option (or argument) that named the file, for the messages.

    Returns:
        The checkpoint dict; ``model`` holds the weights in the current layout.

    Raises:
        InputFileError: no such file.
        CheckpointError: a damaged file, a checkpoint of another kind (a detector, not a
            FreiPose file), a version that cannot be read, or weights that fail the hash
            check.
    """
    path = Path(path)
    ckpt = _read_checkpoint_as(path, POSE_NETWORK, option, CheckpointError)
    version = ckpt.get("version", 0)
    _check_version(path, version)
    if state_hash(ckpt["model"]) != ckpt.get("weights_sha256"):
        raise CheckpointError(f"{path}: the weights do not match their stored hash (corrupt file)")
    num_keypoints = len(ckpt["skeleton"]["keypoints"])
    ckpt["model"] = LOADING_RULES[version](ckpt["model"], num_keypoints)
    return ckpt


def rng_state() -> dict[str, Any]:
    """The states of the torch, numpy, Python (and CUDA) random generators (for resuming)."""
    st = {
        "torch": torch.get_rng_state(),
        "numpy": np.random.get_state(),
        "python": random.getstate(),
    }
    if torch.cuda.is_available():
        st["cuda"] = torch.cuda.get_rng_state_all()
    return st


def set_rng_state(st: dict[str, Any]) -> None:
    """Restore the random generators from :func:`rng_state`."""
    torch.set_rng_state(st["torch"])
    np.random.set_state(st["numpy"])
    random.setstate(st["python"])
    if "cuda" in st and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(st["cuda"])


def training_checkpoint(
    model: nn.Module,
    config: TrainConfig,
    skeleton: Skeleton,
    optimizer: torch.optim.Optimizer,
    rng: dict[str, Any],
    step: int,
    complete: bool,
) -> dict[str, Any]:
    """The checkpoint dict of a training run after ``step`` optimizer steps.

    Args:
        model: the trained network (its weights are copied to the CPU).
        config: the run's resolved config.
        skeleton: the keypoints the network predicts.
        optimizer: the run's optimizer (its state is stored for resuming).
        rng: the random generators' states (:func:`rng_state`; restored on resume).
        step: optimizer steps done.
        complete: the run has done all its steps.

    Returns:
        The dict :func:`serialize_checkpoint` writes (version :data:`CHECKPOINT_VERSION`).
    """
    state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    return {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "freipose_version": __version__,
        "kind": config.model.kind,
        "step": step,
        "complete": complete,
        "config": config_to_dict(config),
        "skeleton": skeleton.to_dict(),
        "model": state,
        "weights_sha256": state_hash(state),
        "optimizer": optimizer.state_dict(),
        "rng": rng,
    }


def serialize_checkpoint(ckpt: dict[str, Any]) -> bytes:
    """Checkpoint dict to bytes (``torch.save``).

    Args:
        ckpt: a checkpoint dict (:func:`training_checkpoint`).

    Returns:
        The file's bytes.
    """
    buf = io.BytesIO()
    torch.save(ckpt, buf)
    return buf.getvalue()


def load_checkpoint(
    path: str | Path,
    device: str | torch.device = "cpu",
    option: str | None = None,
    overrides: InferenceOverrides | None = None,
) -> tuple[nn.Module, TrainConfig, Skeleton]:
    """Load a trained network for inference.

    Args:
        path: a checkpoint written by ``freipose train``.
        device: where the network runs.
        option: the option (or argument) that named the file, for the messages.
        overrides: inference-only settings of ``[model]`` for this run instead of the
            training config's (the returned config holds the values used).

    Returns:
        ``(model, config, skeleton)``: the network in eval mode on ``device``, its
        :class:`TrainConfig` and :class:`freipose.skeleton.Skeleton`.

    Raises:
        InputFileError: no such file.
        CheckpointError: see :func:`read_checkpoint`.
        ConfigError: a negative override.
    """
    ckpt = read_checkpoint(path, option)
    config = config_from_dict(ckpt["config"])
    if overrides is not None:
        config = dataclasses.replace(config, model=overrides.apply(config.model))
    skeleton = skeleton_from_dict(ckpt["skeleton"], f"{path}:skeleton")
    model = build_model(dataclasses.replace(config.model, pretrained=""), len(skeleton.keypoints))
    model.load_state_dict(ckpt["model"])
    model.to(device).eval()
    return model, config, skeleton


def validation_record(path: str | Path) -> dict[str, Any]:
    """What was chosen on validation labels after training (:mod:`freipose.nn.validation`).

    Args:
        path: a checkpoint written by ``freipose train``.

    Returns:
        The ``validation`` record of the checkpoint (the chosen and configured inference
        settings, the errors tried, the uncertainty's scale); empty for a run without
        validation labels.

    Raises:
        InputFileError, CheckpointError: see :func:`read_checkpoint`.
    """
    return dict(read_checkpoint(path).get("validation") or {})
