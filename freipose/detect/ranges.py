"""The allowed range of every number of the training config's ``[detector]`` table.

A value outside its range (or NaN, or infinite) is refused when the table is read, before
a run folder is created, with a message that names the key, the value and the range.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

from freipose.io.toml import Bounds

_PROBABILITY = (0.0, 1.0, "probability")

DETECTOR_RANGES: Mapping[str, Bounds] = MappingProxyType(
    {
        "width": (0.1, 2.0, "backbone width multiplier"),
        "lr": (1e-12, 1.0, "AdamW peak learning rate"),
        "weight_decay": (0.0, 1.0, "AdamW weight decay"),
        "box_margin": (0.0, 2.0, "fraction of the label box's longer side"),
        "min_visible": (0.0, 1.0, "fraction of the box inside the image"),
        "scale": (0.1, 10.0, "zoom factors (min, max)"),
        "hflip": _PROBABILITY,
        "vflip": _PROBABILITY,
        "color": (0.0, 1.0, "fraction"),
        "hue": (0.0, 180.0, "OpenCV hue units, 180 a full turn"),
        "blur": _PROBABILITY,
        "noise": (0.0, 255.0, "grey levels"),
        "eval_fraction": (0.0, 0.99, "fraction of the labeled instants"),
        "cube_size": (10.0, 10000.0, "mm"),
    }
)
