"""Configuration of the pose network and its training (``freipose train CONFIG``).

A training config is a TOML file with the tables ``[data]``, ``[model]``, ``[schedule]``,
``[augment]`` (and ``[detector]``, owned by :mod:`freipose.detect`). ``[model] preset``
picks one of :data:`~freipose.nn.config_presets.PRESETS` (``tiny``, ``small``, ``paper``);
every other key of ``[model]``/``[schedule]``/``[augment]`` overrides a field of the
preset. The complete
resolved config (all defaults filled in) is written next to the checkpoints as
``config.toml`` and stored inside every checkpoint. The schema is in ``docs/formats.md``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from freipose.errors import FreiPoseError
from freipose.io.toml import check_numbers, did_you_mean, read_toml
from freipose.nn.config_presets import PRESETS
from freipose.nn.config_ranges import AUGMENT_RANGES, MODEL_RANGES, SCHEDULE_RANGES
from freipose.nn.config_unlabeled import UnlabeledConfig


class ConfigError(FreiPoseError):
    """A training config is invalid; the message names the key and the allowed values."""


@dataclass(frozen=True)
class ModelConfig:
    """Architecture of the voxel network (and of the triangulation baseline).

    Attributes:
        kind: ``"voxel"`` (FreiPose) or ``"baseline"`` (per-view 2D + robust triangulation).
        crop_size: side of the square view crops in pixels (224 in the paper).
        encoder_channels: channels of the VGG-style 2D encoder blocks.
        encoder_convs: 3x3 convolutions per encoder block.
        encoder_pools: max-pools after the first ``encoder_pools`` blocks; the feature
            stride is ``2**encoder_pools`` (8 in the paper: 224 -> 28).
        feature_channels: channels of the features that are unprojected (128 in the paper).
        norm: ``"group"``, ``"batch"`` or ``"none"`` (the original had none).
        grid_size: voxels per cube edge (64 in the paper).
        cube_size: distance in mm between the outermost voxel centres (400 in the paper).
        crop_fraction: the voxel network's crops enclose the projection of a cube of
            ``crop_fraction * cube_size`` around the centre (1: the whole voxel cube, as in the
            paper). Below 1 the crops spend their pixels on the middle of the cube where the
            animal is; voxels outside a view's crop do not count for that view (the
            unprojection's validity mask), and the other views cover them. The baseline always
            crops the whole cube (:meth:`crop_cube`): it has no other view to fall back on for a
            keypoint outside a crop.
        unet_channels: channels of the 3D U-Net encoder levels (each halves the grid).
        deep_supervision: decode and supervise one volume per U-Net decoder level.
        refine: use the 2D refinement head (P1); otherwise P1 = P0.
        refine_channels: channels of the refinement head and the baseline's 2D head.
        head_levels: decoder steps of both 2D heads above the features, each doubling the
            resolution with the encoder's skip map of that scale; the heads' maps have stride
            ``stride / 2**head_levels`` (2 in the paper: 112 x 112 maps of 224 crops, like the
            original's finest refinement map). Sub-feature-pixel precision of the refinement
            (P1 better than P0) needs the finer maps.
        unproject_levels: decoder steps applied to the features before the unprojection
            (each doubles their resolution with the encoder's skip map of that scale, keeping
            ``feature_channels``): the voxel grid then samples features of stride
            ``stride / 2**unproject_levels``. 0 unprojects the encoder's features (the paper).
        heatmap_sigma: sigma (feature pixels) of the P0 heat maps given to the refinement.
        map_sigma: sigma (map pixels) of the Gaussian target of the 2D heads' map
            cross-entropy loss (``schedule.weight_map``).
        volume_sigma: sigma (voxels) of the Gaussian target of the volumetric
            cross-entropy loss (``schedule.weight_volume``).
        map_window: at inference, the 2D points of the refinement and of the baseline are
            the soft-argmax within this many map pixels (per axis) of each map's peak, so
            that a second mode (the other ear, the other paw) does not pull them toward the
            midpoint; 0 takes the whole map. Training always decodes the whole map.
        fusion_reject: at inference, P1 is fused a second time without the views whose
            refined point lies more than this many voxels (:attr:`voxel_size`) from the first
            fusion's P1 (its distance from the view's ray at P1's depth), so that one view
            that refined onto the wrong part does not pull the point; a keypoint that no view
            supports within it falls back to P0. 0 fuses every view (as in training).
        mask_others: with several animals (labels with ``individual``, ``freipose predict
            --animals``), show each animal's views with the other animals' bodies painted
            grey where they are not over its own (:mod:`freipose.nn.instances`); inference
            first runs the network on the unpainted views, then ``mask_passes`` times with
            the other animals painted at the previous pass's poses.
        mask_radius: half-width in mm of a body around its keypoints for ``mask_others``.
        mask_passes: painted inference passes after the first (``mask_others``).
        pretrained: optional local file with encoder weights (a state dict; loaded
            non-strictly, the missing and unexpected keys are logged).
        init: the weights a new run starts from: ``"base"`` (the base model shipped for
            this architecture in :mod:`freipose.models`; scratch, with a warning, when none
            is shipped), ``"scratch"`` (random initialisation) or the path of a pose
            checkpoint (``model.pt``) of the same architecture. A base or checkpoint of
            another skeleton gives every weight but the keypoint-specific output layers
            (see :mod:`freipose.nn.init`). Resumed runs keep their own weights.
    """

    kind: str = "voxel"
    crop_size: int = 224
    encoder_channels: tuple[int, ...] = (64, 128, 256, 512, 512)
    encoder_convs: tuple[int, ...] = (2, 2, 4, 4, 2)
    encoder_pools: int = 3
    feature_channels: int = 128
    norm: str = "group"
    grid_size: int = 64
    cube_size: float = 400.0
    crop_fraction: float = 1.0
    unet_channels: tuple[int, ...] = (32, 64, 64, 64)
    deep_supervision: bool = True
    refine: bool = True
    refine_channels: int = 128
    head_levels: int = 2
    unproject_levels: int = 0
    heatmap_sigma: float = 2.0
    map_sigma: float = 1.0
    volume_sigma: float = 1.0
    map_window: int = 3
    fusion_reject: float = 1.0
    mask_others: bool = False
    mask_radius: float = 20.0
    mask_passes: int = 2
    pretrained: str = ""
    init: str = "base"

    def __post_init__(self) -> None:
        check_numbers(self, "model", MODEL_RANGES, ConfigError)
        if self.kind not in ("voxel", "baseline"):
            raise ConfigError(f"model.kind must be 'voxel' or 'baseline', got {self.kind!r}")
        if not 1 <= self.mask_passes <= 10:
            raise ConfigError(
                f"model.mask_passes must be in 1..10 (painted passes after the first), "
                f"got {self.mask_passes}"
            )
        if self.norm not in ("group", "batch", "none"):
            raise ConfigError(f"model.norm must be 'group', 'batch' or 'none', got {self.norm!r}")
        if len(self.encoder_channels) != len(self.encoder_convs) or not self.encoder_channels:
            raise ConfigError(
                "model.encoder_channels and model.encoder_convs must be non-empty and of equal "
                f"length, got {list(self.encoder_channels)} and {list(self.encoder_convs)}"
            )
        if not 1 <= self.encoder_pools <= len(self.encoder_channels):
            raise ConfigError(
                f"model.encoder_pools must be in 1..{len(self.encoder_channels)}, "
                f"got {self.encoder_pools}"
            )
        if not 1 <= self.head_levels <= self.encoder_pools:
            raise ConfigError(
                f"model.head_levels must be in 1..encoder_pools ({self.encoder_pools}), "
                f"got {self.head_levels}"
            )
        if not 0 <= self.unproject_levels <= self.encoder_pools:
            raise ConfigError(
                f"model.unproject_levels must be in 0..encoder_pools ({self.encoder_pools}), "
                f"got {self.unproject_levels}"
            )
        if self.map_window < 0:
            raise ConfigError(
                f"model.map_window must be >= 0 (map pixels; 0: the whole map), "
                f"got {self.map_window}"
            )
        if self.crop_size % self.stride:
            raise ConfigError(
                f"model.crop_size ({self.crop_size}) must be a multiple of the feature stride "
                f"{self.stride} (2**encoder_pools)"
            )
        levels = len(self.unet_channels)
        if levels < 1 or self.grid_size % (2**levels):
            raise ConfigError(
                f"model.grid_size ({self.grid_size}) must be divisible by 2**len(unet_channels) "
                f"= {2**levels}"
            )
        if not self.init:
            raise ConfigError(
                'model.init must be "base", "scratch" or the path of a pose checkpoint, got ""'
            )
        if self.pretrained and self.init not in ("base", "scratch"):
            raise ConfigError(
                f"model.init = {self.init!r} (a checkpoint) and model.pretrained (encoder "
                "weights) both give starting weights; set only one of them"
            )

    @property
    def stride(self) -> int:
        """Feature stride: crop pixels per feature pixel."""
        return 2**self.encoder_pools

    @property
    def crop_cube(self) -> float:
        """Edge (mm) of the cube whose projection each crop encloses."""
        return self.cube_size * (self.crop_fraction if self.kind == "voxel" else 1.0)

    @property
    def map_stride(self) -> float:
        """Crop pixels per pixel of the 2D heads' maps."""
        return self.stride / 2**self.head_levels

    @property
    def feature_size(self) -> int:
        """Side of the feature maps."""
        return self.crop_size // self.stride

    @property
    def voxel_size(self) -> float:
        """Voxel spacing in mm."""
        return self.cube_size / (self.grid_size - 1)


@dataclass(frozen=True)
class InferenceOverrides:
    """The ``[model]`` settings that act at inference only, changed for one run.

    A trained network is the same with any of them, so ``freipose eval`` and ``predict``
    may change them without retraining. None keeps the checkpoint's value.

    Attributes:
        fusion_reject: ``model.fusion_reject`` (voxels; 0: P1 fuses every view).
        map_window: ``model.map_window`` (map pixels; 0: the 2D points are the soft-argmax
            of the whole map).
    """

    fusion_reject: float | None = None
    map_window: int | None = None

    def apply(self, model: ModelConfig) -> ModelConfig:
        """``model`` with the settings that are not None replaced.

        Raises:
            ConfigError: a negative value.
        """
        changes = {k: v for k, v in dataclasses.asdict(self).items() if v is not None}
        return dataclasses.replace(model, **changes) if changes else model


def inference_settings(model: ModelConfig, refine: bool = True) -> dict[str, float]:
    """The inference-only settings that shape a network's reported pose (for provenance).

    Args:
        model: the config the network ran with.
        refine: whether a voxel network's P1 is reported (P0 depends on neither setting).

    Returns:
        ``{"map_window": ..., "fusion_reject": ...}`` with the settings that act: both for
        a voxel network's P1, ``map_window`` for the baseline, none for P0.
    """
    if model.kind != "voxel":
        return {"map_window": model.map_window}
    return {"map_window": model.map_window, "fusion_reject": model.fusion_reject} if refine else {}


@dataclass(frozen=True)
class ScheduleConfig:
    """Optimisation schedule (Adam with step decay).

    ``steps`` optimizer steps of ``batch_size`` multi-view samples (the global batch; with
    DDP each of W processes takes ``batch_size / W``). The learning rate is
    ``lr * lr_decay ** (step // lr_decay_steps)``. The refinement head is frozen (its loss
    weighted 0) for the first ``refine_start`` fraction of the steps, as in the original.
    ``amp``: bfloat16 autocast on a GPU with bfloat16 units (compute capability 8.0 or
    newer); training runs in fp32 elsewhere.
    """

    steps: int = 60000
    batch_size: int = 1
    lr: float = 1e-4
    lr_decay: float = 0.1
    lr_decay_steps: int = 30000
    refine_start: float = 0.5
    weight_p0: float = 1.0
    weight_aux: float = 0.5
    weight_volume: float = 0.1
    weight_2d: float = 1.0
    weight_conf: float = 0.1
    weight_map: float = 0.1
    weight_p1: float = 1.0
    checkpoint_every: int = 1000
    eval_every: int = 1000
    eval_samples: int = 64
    log_every: int = 10
    seed: int = 0
    num_workers: int = 0
    amp: bool = True

    def __post_init__(self) -> None:
        check_numbers(self, "schedule", SCHEDULE_RANGES, ConfigError)
        for name in (
            "steps",
            "batch_size",
            "lr_decay_steps",
            "checkpoint_every",
            "eval_every",
            "log_every",
        ):
            if getattr(self, name) < 1:
                raise ConfigError(f"schedule.{name} must be >= 1, got {getattr(self, name)}")

    def lr_at(self, step: int) -> float:
        """Learning rate used for optimizer step ``step`` (0-based)."""
        return self.lr * self.lr_decay ** (step // self.lr_decay_steps)

    def refine_active(self, step: int) -> bool:
        """Whether the refinement head trains at ``step``."""
        return step >= int(round(self.refine_start * self.steps))


@dataclass(frozen=True)
class AugmentConfig:
    """Training augmentation. Geometric changes are compensated in the crop cameras.

    ``grid_rotation`` (degrees): the voxel grid of each training sample is turned by a
    random angle in ``[-grid_rotation, grid_rotation]`` about the world's up (the calibration's
    ``up``, else estimated from the labels, else world z), so the 3D network cannot tie
    keypoints to absolute directions (evaluation uses the unrotated grid).
    ``refine_jitter`` (mm): std of Gaussian noise added per keypoint and axis to P0 before it
    is given to the refinement head during training, so the head learns to correct P0.
    ``max_views``: each training sample keeps a random subset of at most this many of its
    views (0: all). A step then costs about as many views' encoder and unprojection work,
    and the networks learn to work with the views a frame actually has.
    """

    enabled: bool = True
    center_jitter: float = 10.0
    grid_rotation: float = 180.0
    refine_jitter: float = 6.0
    rotation: float = 7.5
    zoom: tuple[float, float] = (0.9, 1.1)
    shift: float = 5.0
    hue: float = 10.0
    brightness: float = 0.15
    contrast: float = 0.15
    blur_sigma: float = 0.7
    noise: float = 0.02
    salt_pepper: float = 0.001
    max_views: int = 0

    def __post_init__(self) -> None:
        check_numbers(self, "augment", AUGMENT_RANGES, ConfigError)
        if len(self.zoom) != 2 or self.zoom[0] > self.zoom[1]:
            raise ConfigError(
                f"augment.zoom must be [min, max] with min <= max, got {list(self.zoom)}"
            )
        if self.max_views < 0 or self.max_views == 1:
            raise ConfigError(
                f"augment.max_views must be 0 (every view) or at least 2, got {self.max_views}"
            )


@dataclass(frozen=True)
class DataConfig:
    """Where the training data is. Relative paths are relative to the config file.

    ``validation_labels``: a validation part of the labels (never the held-out test labels)
    on which the inference settings are chosen and the uncertainty calibrated after
    training (:mod:`freipose.nn.validation`); empty: the configured settings are kept.
    """

    PATH_KEYS: ClassVar[tuple[str, ...]] = ("labels", "eval_labels", "validation_labels", "root")

    labels: str = ""
    eval_labels: str = ""
    validation_labels: str = ""
    root: str = ""
    cameras: tuple[str, ...] = ()
    skeleton: str = ""


@dataclass(frozen=True)
class TrainConfig:
    """A complete training config (see the module docstring).

    ``cube_auto``: ``model.cube_size`` was ``"auto"`` or absent; training sizes the cube
    from its labels (:func:`freipose.nn.sizing.resolve_cube`), until then it holds the
    preset's value. ``unlabeled``: :mod:`freipose.nn.config_unlabeled`.
    """

    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    preset: str = "paper"
    extra: Mapping[str, Any] = field(default_factory=dict)
    cube_auto: bool = False
    unlabeled: UnlabeledConfig = field(default_factory=UnlabeledConfig)


def _fields(cls: type) -> dict[str, dataclasses.Field]:
    """The dataclass fields of ``cls`` by name."""
    return {f.name: f for f in dataclasses.fields(cls)}


def _coerce(cls: type, values: Mapping[str, Any], table: str) -> dict[str, Any]:
    """Check the keys and value types of the TOML table ``table`` against the fields of ``cls``.

    Lists become tuples and integers floats where the field's default is one.

    Raises:
        ConfigError: an unknown key (with the closest known one) or a value of the wrong type.
    """
    known = _fields(cls)
    out: dict[str, Any] = {}
    for key, value in values.items():
        if key not in known:
            raise ConfigError(
                f"unknown key {table}.{key}{did_you_mean(key, known) or ';'} allowed keys: "
                f"{sorted(known)} (see docs/formats.md)"
            )
        default = known[key].default
        factory = known[key].default_factory
        if default is dataclasses.MISSING and callable(factory):
            default = factory()
        if isinstance(default, tuple):
            if not isinstance(value, (list, tuple)):
                raise ConfigError(f"{table}.{key} must be a list, got {value!r}")
            value = tuple(value)
        elif isinstance(default, bool):
            if not isinstance(value, bool):
                raise ConfigError(f"{table}.{key} must be true or false, got {value!r}")
        elif isinstance(default, int):
            if isinstance(value, bool) or not isinstance(value, int):
                raise ConfigError(f"{table}.{key} must be an integer, got {value!r}")
        elif isinstance(default, float):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f"{table}.{key} must be a number, got {value!r}")
            value = float(value)
        elif isinstance(default, str) and not isinstance(value, str):
            raise ConfigError(f"{table}.{key} must be a string, got {value!r}")
        out[key] = value
    return out


def _stretched_decay(preset: Mapping[str, Any], table: dict[str, Any]) -> dict[str, Any]:
    """``[schedule]`` with ``lr_decay_steps`` scaled to its ``steps`` when only those are set.

    The presets drop the learning rate at a fixed share of their steps (``small``: 2000 of
    3000, ``paper``: 30000 of 60000); a run of other length keeps that share instead of
    never reaching the drop (or reaching it at once).
    """
    if "steps" not in table or "lr_decay_steps" in table:
        return table
    defaults = ScheduleConfig()
    steps = int(preset.get("steps", defaults.steps))
    decay = int(preset.get("lr_decay_steps", defaults.lr_decay_steps))
    return {**table, "lr_decay_steps": max(1, round(table["steps"] * decay / steps))}


_TABLES = ("data", "model", "schedule", "augment", "unlabeled")


def config_from_dict(data: Mapping[str, Any]) -> TrainConfig:
    """Build a :class:`TrainConfig` from the TOML structure (presets applied, validated).

    Args:
        data: the TOML tables (``[data]``, ``[model]``, ``[schedule]``, ``[augment]``; the
            ``[detector]`` and ``[predict]`` tables are kept in ``extra``).

    Returns:
        The resolved config.

    Raises:
        ConfigError: an unknown table, key or preset, or an invalid value.
    """
    known_tables = {"data", "model", "schedule", "augment", "unlabeled", "detector", "predict"}
    unknown = sorted(set(data) - known_tables)
    if unknown:
        hint = did_you_mean(unknown[0], known_tables) or ";"
        raise ConfigError(
            f"unknown config tables {unknown}{hint} allowed: {sorted(known_tables)} "
            "(see docs/formats.md)"
        )
    model_tbl = dict(data.get("model", {}))
    preset = str(model_tbl.pop("preset", "paper"))
    if preset not in PRESETS:
        raise ConfigError(f"model.preset must be one of {sorted(PRESETS)}, got {preset!r}")
    p_model, p_sched = PRESETS[preset]
    cube_auto = model_tbl.get("cube_size", "auto") == "auto"  # sized from the labels
    if cube_auto:
        model_tbl.pop("cube_size", None)
    model = ModelConfig(**{**p_model, **_coerce(ModelConfig, model_tbl, "model")})
    sched_tbl = _coerce(ScheduleConfig, dict(data.get("schedule", {})), "schedule")
    sched = ScheduleConfig(**{**p_sched, **_stretched_decay(p_sched, sched_tbl)})
    aug = AugmentConfig(**_coerce(AugmentConfig, dict(data.get("augment", {})), "augment"))
    dat = DataConfig(**_coerce(DataConfig, dict(data.get("data", {})), "data"))
    try:
        unl = UnlabeledConfig(
            **_coerce(UnlabeledConfig, dict(data.get("unlabeled", {})), "unlabeled")
        )
    except ValueError as exc:
        raise ConfigError(str(exc)) from exc
    extra = {k: v for k, v in data.items() if k not in _TABLES}
    return TrainConfig(dat, model, sched, aug, preset, extra, cube_auto, unl)


def config_to_dict(config: TrainConfig) -> dict[str, Any]:
    """The complete config as TOML-ready nested dicts (every default written out).

    Args:
        config: a resolved config.

    Returns:
        The tables (the inverse of :func:`config_from_dict`).
    """

    def plain(obj: Any) -> dict[str, Any]:
        return {
            k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(obj).items()
        }

    out: dict[str, Any] = {
        "data": plain(config.data),
        "model": {"preset": config.preset, **plain(config.model)},
        "schedule": plain(config.schedule),
        "augment": plain(config.augment),
        "unlabeled": plain(config.unlabeled),
    }
    for k, v in config.extra.items():
        out[k] = dict(v) if isinstance(v, Mapping) else v
    return out


def load_config(path: str | Path) -> TrainConfig:
    """Read a training config TOML file.

    Args:
        path: the config file.

    Returns:
        The resolved config.

    Raises:
        InputFileError: no such file.
        ConfigError: invalid TOML or invalid values (the message names the key).
    """
    path = Path(path)
    data = read_toml(path, "training config", ConfigError)
    try:
        return config_from_dict(data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from exc
    except TypeError as exc:  # pragma: no cover - dataclass signature mismatch
        raise ConfigError(f"{path}: {exc}") from exc


def model_config_from_dict(data: Mapping[str, Any]) -> ModelConfig:
    """A :class:`ModelConfig` from a plain dict (e.g. stored in a checkpoint).

    Args:
        data: the ``[model]`` table (``preset`` is ignored).

    Returns:
        The model config (without the preset's values).

    Raises:
        ConfigError: an unknown key or an invalid value.
    """
    d = {k: v for k, v in data.items() if k != "preset"}
    return ModelConfig(**_coerce(ModelConfig, d, "model"))
