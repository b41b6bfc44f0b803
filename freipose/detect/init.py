"""The starting weights of a new detector training (``[detector] init``).

``init = "base"`` (the default) starts from the detector that :mod:`freipose.models` ships
for the run's backbone width and neck channels (any input size: the network is fully
convolutional); when none is shipped for them, the run starts from scratch with a warning.
``init = "scratch"`` is the random initialisation; a path starts from that detector
checkpoint (``detector.pt``), which must have the same width and neck channels. With
``backbone_weights`` given, ``init = "base"`` leaves the base out (those weights are the
start).
"""

from __future__ import annotations

import logging
from pathlib import Path

from freipose.detect.detector import load_checkpoint
from freipose.detect.model import DetectorNet
from freipose.errors import FreiPoseError
from freipose.models import base_file, find_base, shipped_bases

log = logging.getLogger(__name__)

#: the detector settings that fix the shapes of its weights
DETECTOR_ARCH_KEYS = ("width", "neck_channels")


class DetectorInitError(FreiPoseError):
    """``[detector] init`` names a checkpoint of another architecture."""


def initialize_detector(net: DetectorNet, init: str, backbone_weights: str = "") -> str:
    """Give a newly built detector the starting weights that ``init`` names.

    Args:
        net: the new network.
        init: ``"base"``, ``"scratch"`` or the path of a detector checkpoint.
        backbone_weights: the ``[detector] backbone_weights`` file ('' for none).

    Returns:
        ``"scratch"``, ``"base:<name>"`` or the checkpoint's path.

    Raises:
        InputFileError: ``init`` names a file that does not exist.
        DetectorCheckpointError: the file is damaged or not a detector checkpoint.
        DetectorInitError: the checkpoint has another width or neck.
    """
    if init == "scratch":
        return "scratch"
    arch = net.config.to_dict()
    if init == "base":
        if backbone_weights:
            log.info("[detector] backbone_weights given: not starting from a base detector")
            return "scratch"
        base = find_base("detector", arch, DETECTOR_ARCH_KEYS)
        if base is None:
            have = ", ".join(
                f"width {b.architecture.get('width')}, neck_channels "
                f"{b.architecture.get('neck_channels')}"
                for b in shipped_bases()
                if b.kind == "detector"
            )
            log.warning(
                '[detector] init = "base": no base detector is shipped for width %s and '
                "neck_channels %s (shipped: %s); training starts from scratch (set [detector] "
                'init = "scratch" to silence this)',
                net.config.width, net.config.neck_channels, have or "none",
            )  # fmt: skip
            return "scratch"
        with base_file(base) as path:
            ckpt = load_checkpoint(path, option="[detector] init")
        source = f"base:{base.name}"
    else:
        ckpt = load_checkpoint(Path(init), option="[detector] init")
        source = init
    diff = [k for k in DETECTOR_ARCH_KEYS if ckpt["config"].get(k) != arch[k]]
    if diff:
        raise DetectorInitError(
            f"[detector] init: {init} has "
            + ", ".join(f"{k} {ckpt['config'].get(k)} (this config: {arch[k]})" for k in diff)
            + '; set the same [detector] width and neck_channels, or init = "scratch"'
        )
    net.load_state_dict(ckpt["model"])
    log.info("detector: starting from %s (step %s)", source, ckpt.get("step"))
    return source
