"""The presets of the training config (``[model] preset``): model and schedule overrides.

``tiny`` (tests and smoke runs), ``small`` (the shipped base models, CPU-sized) and ``paper``
(the defaults of :class:`~freipose.nn.config.ModelConfig` and
:class:`~freipose.nn.config.ScheduleConfig`, the published network).
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

# Presets: (model overrides, schedule overrides).
_PRESETS: dict[str, tuple[dict[str, Any], dict[str, Any]]] = {
    "tiny": (
        dict(
            crop_size=32,
            encoder_channels=(8, 8, 16),
            encoder_convs=(1, 1, 1),
            encoder_pools=2,
            feature_channels=8,
            grid_size=8,
            unet_channels=(8,),
            refine_channels=8,
            head_levels=1,
            heatmap_sigma=1.0,
        ),
        dict(
            steps=20,
            batch_size=2,
            lr=2e-3,
            lr_decay_steps=1000,
            checkpoint_every=10,
            eval_every=10,
            eval_samples=4,
            log_every=1,
            amp=False,
        ),
    ),
    "small": (
        dict(
            crop_size=128,
            encoder_channels=(16, 32, 48, 64),
            encoder_convs=(1, 1, 2, 1),
            encoder_pools=3,
            feature_channels=32,
            grid_size=32,
            cube_size=320.0,
            unet_channels=(16, 32, 32),
            refine_channels=32,
            head_levels=2,
            unproject_levels=1,
            crop_fraction=0.6,
            heatmap_sigma=1.5,
        ),
        dict(
            steps=3000,
            refine_start=0.2,
            batch_size=2,
            lr=1e-3,
            lr_decay_steps=2000,
            checkpoint_every=250,
            eval_every=250,
            eval_samples=24,
            log_every=10,
        ),
    ),
    "paper": ({}, {}),
}
PRESETS: Mapping[str, tuple[Mapping[str, Any], Mapping[str, Any]]] = MappingProxyType(
    {k: (MappingProxyType(m), MappingProxyType(sc)) for k, (m, sc) in _PRESETS.items()}
)
