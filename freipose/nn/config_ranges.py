"""The allowed range of every number of the training config's tables.

The tables: ``[model]``, ``[schedule]``, ``[augment]`` and ``[unlabeled]``.

A value outside its range (or NaN, or infinite) is refused when the config is read, before
a run folder is created, with a message that names the key, the value and the range. The
ranges are wide: they keep out what cannot train (a learning rate of 1e6, a cube of
infinite size, NaN weights), not unusual choices.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

from freipose.io.toml import Bounds

_SIGMA = 0.1, 20.0

MODEL_RANGES: Mapping[str, Bounds] = MappingProxyType(
    {
        "cube_size": (10.0, 10000.0, "mm between the outermost voxel centres"),
        "crop_fraction": (0.1, 1.0, "of the cube"),
        "heatmap_sigma": (*_SIGMA, "feature pixels"),
        "map_sigma": (*_SIGMA, "map pixels"),
        "volume_sigma": (*_SIGMA, "voxels"),
        "fusion_reject": (0.0, 1000.0, "voxels; 0: fuse every view"),
        "mask_radius": (0.0, 1000.0, "mm around a body's keypoints"),
    }
)

_WEIGHT = (0.0, 1000.0, "loss weight")

SCHEDULE_RANGES: Mapping[str, Bounds] = MappingProxyType(
    {
        "lr": (1e-12, 1.0, "Adam learning rate"),
        "lr_decay": (1e-6, 1.0, "factor every lr_decay_steps"),
        "refine_start": (0.0, 1.0, "fraction of the steps"),
        **{f"weight_{k}": _WEIGHT for k in ("p0", "aux", "volume", "2d", "conf", "map", "p1")},
    }
)

AUGMENT_RANGES: Mapping[str, Bounds] = MappingProxyType(
    {
        "center_jitter": (0.0, 1000.0, "mm, std of the cube-centre jitter"),
        "grid_rotation": (0.0, 180.0, "degrees"),
        "refine_jitter": (0.0, 1000.0, "mm, std of the noise added to P0"),
        "rotation": (0.0, 180.0, "degrees"),
        "zoom": (0.1, 10.0, "scale factors (min, max)"),
        "shift": (0.0, 1000.0, "pixels"),
        "hue": (0.0, 180.0, "degrees"),
        "brightness": (0.0, 1.0, "fraction"),
        "contrast": (0.0, 1.0, "fraction"),
        "blur_sigma": (0.0, 20.0, "pixels"),
        "noise": (0.0, 1.0, "std, fraction of the grey range"),
        "salt_pepper": (0.0, 1.0, "fraction of the pixels"),
    }
)

UNLABELED_RANGES: Mapping[str, Bounds] = MappingProxyType(
    {
        "share": (0.0, 0.95, "share of the instants of each step that are unlabeled"),
        "start": (0.0, 1.0, "fraction of the steps before the unlabeled losses act"),
        "robust_scale": (1e-3, 100.0, "voxels (3D) and feature pixels (2D)"),
        "teacher_decay": (0.0, 0.99999, "EMA factor per step"),
        "teacher_agreement": (1e-3, 100.0, "feature pixels"),
        **{
            f"weight_{k}": _WEIGHT
            for k in ("multiview", "p0p1", "temporal", "equivariance", "bones", "teacher")
        },
    }
)
