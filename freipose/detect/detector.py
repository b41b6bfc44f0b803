"""The trained detector: loading a checkpoint and proposing boxes in full frames."""

from __future__ import annotations

import io
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from freipose import __version__
from freipose.detect.base import Candidates, DetectConfigError
from freipose.detect.boxes import transform_boxes
from freipose.detect.model import DetectorConfig, DetectorNet, decode, letterbox_affine, to_tensor
from freipose.errors import InputFileError
from freipose.io.atomic import atomic_path
from freipose.io.checkpoints import (
    DETECTOR,
    DETECTOR_FORMAT,
    KIND_NAMES,
    UNSAFE,
    CheckpointFileError,
    CheckpointUse,
    load_safely,
    read_checkpoint_as,
)

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = DETECTOR_FORMAT
CHECKPOINT_VERSION = 1
PAD_VALUE = 114  # grey padding of letterboxed inputs


class DetectorCheckpointError(CheckpointFileError):
    """A detector checkpoint is missing, unreadable or of another kind."""


def resolve_device(device: str | torch.device | None) -> torch.device:
    """``"auto"``/None -> CUDA when available else CPU; otherwise the named device (checked)."""
    if device is None or str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise DetectConfigError(
            f"device {device!r} was asked for but no CUDA GPU is available; use --device cpu"
        )
    return dev


def letterbox(image: np.ndarray, input_size: int) -> np.ndarray:
    """Scale a BGR image (H, W, 3) into the top-left of a grey square (S, S, 3)."""
    h, w = image.shape[:2]
    s = input_size / max(w, h)
    nw, nh = max(1, round(w * s)), max(1, round(h * s))
    small = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    out = np.full((input_size, input_size, 3), PAD_VALUE, np.uint8)
    out[:nh, :nw] = small[:input_size, :input_size]
    return out


class Detector:
    """A trained single-class detector (a :class:`~freipose.detect.base.BoxSource`).

    Args:
        net: the network (moved to ``device`` and put in eval mode).
        device: where inference runs.
        top_k: most candidates kept per image.
        min_score: lowest heat-map score kept.
    """

    def __init__(
        self,
        net: DetectorNet,
        device: str | torch.device = "cpu",
        top_k: int = 5,
        min_score: float = 0.05,
        metadata: dict[str, Any] | None = None,
    ):
        self.device = resolve_device(device)
        self.net = net.to(self.device).eval()
        self.config: DetectorConfig = net.config
        self.top_k = top_k
        self.min_score = min_score
        self.metadata = dict(metadata or {})

    @classmethod
    def load(
        cls,
        path: str | Path,
        device: str | torch.device = "cpu",
        option: str | None = None,
        **kwargs: Any,
    ) -> Detector:
        """Load a checkpoint written by ``freipose train CONFIG --stage detector``.

        ``option`` (e.g. ``"--detector"``) names the option that gave ``path`` in the
        message for a file of another kind; ``kwargs`` go to the constructor.
        """
        ckpt = load_checkpoint(path, option=option)
        net = DetectorNet(DetectorConfig(**ckpt["config"]))
        net.load_state_dict(ckpt["model"])
        meta = {k: ckpt[k] for k in ("metrics", "step", "box_margin") if k in ckpt}
        return cls(net, device, metadata=meta, **kwargs)

    def save(self, path: str | Path) -> None:
        """Write the weights and architecture (no optimizer state) as a checkpoint."""
        save_checkpoint(path, self.net, extra=self.metadata)

    def preprocess(self, images: Sequence[np.ndarray]) -> tuple[torch.Tensor, list[np.ndarray]]:
        """Letterboxed input tensor (B, 3, S, S) and per image the inverse affine (3x3)."""
        s = self.config.input_size
        arrs, inv = [], []
        for img in images:
            img = np.asarray(img)
            if img.ndim == 2:
                img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
            if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
                raise ValueError(f"images must be BGR uint8 (H, W, 3), got {img.dtype} {img.shape}")
            arrs.append(letterbox(img, s))
            inv.append(np.linalg.inv(letterbox_affine((img.shape[1], img.shape[0]), s)))
        return to_tensor(np.stack(arrs)), inv

    @torch.no_grad()
    def propose(
        self,
        images: Sequence[np.ndarray],
        cameras: Sequence[str] | None = None,
        batch_size: int = 32,
    ) -> list[Candidates]:
        """Candidate boxes (full-image pixels) per image; ``cameras`` is accepted and unused."""
        out: list[Candidates] = []
        for i in range(0, len(images), batch_size):
            x, inv = self.preprocess(images[i : i + batch_size])
            heat, size, off = self.net(x.to(self.device))
            for (boxes, scores), A in zip(
                decode(heat, size, off, self.top_k, self.min_score), inv, strict=True
            ):
                out.append(Candidates(transform_boxes(boxes, A), scores))
        return out


def save_checkpoint(
    path: str | Path, net: DetectorNet, extra: dict[str, Any] | None = None
) -> None:
    """Write ``{"format", "version", "kind", "config", "model", ...extra}`` atomically.

    ``kind`` is ``"detector_training_state"`` when ``extra`` holds an ``optimizer`` state
    (a resumable ``detector_last.pt``), else ``"detector"``.
    """
    extra = extra or {}
    state = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "freipose_version": __version__,
        "kind": "detector_training_state" if "optimizer" in extra else "detector",
        "config": net.config.to_dict(),
        "model": {k: v.detach().cpu() for k, v in net.state_dict().items()},
    }
    state.update(extra)
    buf = io.BytesIO()  # torch.save to a path turns a full disk into a RuntimeError
    torch.save(state, buf)
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.getvalue())


def load_checkpoint(
    path: str | Path, use: CheckpointUse = DETECTOR, option: str | None = None
) -> dict[str, Any]:
    """Read and check a detector checkpoint (tensors on the CPU), without running its code.

    Args:
        path: the checkpoint.
        use: the accepted kinds (default: a detector, with or without training state).
        option: the option that named the file (e.g. ``"--detector"``), for the message.

    Returns:
        The checkpoint dict.

    Raises:
        InputFileError: no such file.
        DetectorCheckpointError: a damaged file, a file of another kind (e.g. a pose
            network; see :func:`freipose.io.checkpoints.checkpoint_kind`) or a newer
            version.
    """
    p = Path(path)
    if not p.is_file():
        raise InputFileError(
            f"{p}: detector checkpoint not found; train one with "
            "`freipose train CONFIG --stage detector`"
        )
    ckpt = read_checkpoint_as(p, use, option, DetectorCheckpointError)
    if int(ckpt.get("version", 0)) > CHECKPOINT_VERSION:
        raise DetectorCheckpointError(
            f"{p}: checkpoint version {ckpt['version']} is newer than this FreiPose reads "
            f"({CHECKPOINT_VERSION}); upgrade FreiPose"
        )
    return ckpt


def load_backbone_weights(net: DetectorNet, path: str | Path) -> tuple[int, int]:
    """Initialise the backbone from a local file (a state dict, or a detector checkpoint).

    Keys may be bare (``stem.0.weight``) or prefixed with ``backbone.``; tensors whose name
    or shape does not match are skipped. Returns ``(loaded, skipped)`` counts and raises
    ``DetectorCheckpointError`` when nothing matches.
    """
    p = Path(path)
    if not p.is_file():
        raise InputFileError(f"{p}: backbone weights file not found")
    state = load_safely(p, error=DetectorCheckpointError)
    if state is UNSAFE:
        raise DetectorCheckpointError(
            f"{p} is {KIND_NAMES['other']}; detector.backbone_weights takes a state dict of "
            "tensors or a detector checkpoint"
        )
    if isinstance(state, dict) and "model" in state and isinstance(state["model"], dict):
        state = state["model"]
    if isinstance(state, dict) and "state_dict" in state and isinstance(state["state_dict"], dict):
        state = state["state_dict"]
    if not isinstance(state, dict):
        raise DetectorCheckpointError(
            f"{p}: expected a dict of tensors, found {type(state).__name__}"
        )
    own = net.backbone.state_dict()
    new = {}
    skipped = 0
    for k, v in state.items():
        key = k[len("backbone.") :] if k.startswith("backbone.") else k
        if key in own and isinstance(v, torch.Tensor) and v.shape == own[key].shape:
            new[key] = v
        else:
            skipped += 1
    if not new:
        raise DetectorCheckpointError(
            f"{p}: none of its {len(state)} tensors matches the detector backbone (width "
            f"{net.config.width}); expected names like {next(iter(own))!r}"
        )
    own.update(new)
    net.backbone.load_state_dict(own)
    log.info("backbone: loaded %d tensors from %s (%d skipped)", len(new), p, skipped)
    return len(new), skipped
