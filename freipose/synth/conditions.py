"""Conditions of real rigs and domain randomisation: the extra :class:`SceneConfig` settings.

:class:`~freipose.synth.scene.SceneConfig` holds them as plain fields (``scene.toml`` keys);
this module checks them (:func:`check_conditions`), turns the photometric ones into the
renderer's :class:`~freipose.synth.look.SceneStyle`, and draws a whole varied scene from the
seed (:func:`randomized`, what ``randomize = true`` does):

* ``animal`` ``"rat"`` / ``"mouse"`` and ``animal_scale`` (body size, rat = 1);
* ``grayscale`` (every camera, or a list of camera names), ``lens`` (``standard``,
  ``fisheye``, ``pinhole``), ``layout`` of the default rig (``ring``, ``above``, ``side``,
  ``below``: one camera under a transparent floor; ``arc``: all on one side, never drawn by
  :func:`randomized`);
* ``walls`` ``"opaque"`` / ``"acrylic"`` (transparent: the animal is seen, and labeled,
  through them);
* ``reflections`` (mirror images of the animal in the walls), ``rest_fraction`` (resting
  phases), ``floor`` (``mat``, ``bedding``), ``floor_color`` / ``wall_color`` (RGB 0..1),
  ``brightness``, ``contrast``, ``light_gradient``, ``blur`` (px), ``noise_level``;
* ``label_files`` (``sleap``, ``dlc``: per-camera label files of predicted instances) with
  ``label_noise_px``.

Every default reproduces the classic scene exactly; ``to_dict`` leaves the settings at their
defaults out of ``scene.toml`` (see :data:`CONDITION_DEFAULTS`).
"""

from __future__ import annotations

import math
from dataclasses import fields, replace
from typing import Any

import numpy as np

from freipose.synth.errors import SynthError
from freipose.synth.look import SceneStyle
from freipose.synth.rig import LAYOUTS  # randomized draws the first four

# a freipose.synth.scene.SceneConfig (which imports this module; not imported back)
SceneConfig = Any

ANIMALS = ("rat", "mouse")
ANIMAL_SCALE = {"rat": 1.0, "mouse": 0.42}  # body size factor (rat: ~23 cm nose to tail root)
LENSES = ("standard", "fisheye", "pinhole")
FLOORS = ("mat", "bedding")
WALLS = ("opaque", "acrylic")
LABEL_FORMATS = ("sleap", "dlc", "sleap-session")
COAT_MIXES = ("random", "same", "different")  # how the coats of several animals are drawn
MAX_ANIMALS = 4

# The extra settings and their defaults (the classic scene); left out of scene.toml there.
CONDITION_DEFAULTS: dict[str, Any] = {
    "animal": "rat",
    "animal_scale": None,
    "grayscale": False,
    "lens": "standard",
    "layout": "ring",
    "reflections": 0.0,
    "walls": "opaque",
    "rest_fraction": 0.0,
    "floor": "mat",
    "floor_color": None,
    "wall_color": None,
    "brightness": 1.0,
    "contrast": 1.0,
    "light_gradient": 0.0,
    "blur": 0.0,
    "noise_level": 1.0,
    "label_files": (),
    "label_noise_px": 1.0,
    "randomize": False,
    "animals": 1,
    "coat_mix": "random",
    "animal_scales": None,
}

_RANGES = {  # (low, high) of the numeric settings
    "animal_scale": (0.3, 1.5),
    "reflections": (0.0, 0.9),
    "rest_fraction": (0.0, 0.95),
    "brightness": (0.2, 3.0),
    "contrast": (0.2, 3.0),
    "light_gradient": (0.0, 0.9),
    "blur": (0.0, 10.0),
    "noise_level": (0.0, 10.0),
    "label_noise_px": (0.0, 50.0),
}


def _choice(cfg: SceneConfig, key: str, options: tuple[str, ...]) -> None:
    value = getattr(cfg, key)
    if value not in options:
        raise SynthError(f"{key} must be one of {', '.join(options)}, got {value!r}")


def _colour(cfg: SceneConfig, key: str) -> tuple[float, float, float] | None:
    value = getattr(cfg, key)
    if value is None:
        return None
    try:
        rgb = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        rgb = ()
    if len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb):
        raise SynthError(f"{key} must be [r, g, b] with values in 0..1, got {value!r}")
    return (rgb[0], rgb[1], rgb[2])


def check_conditions(cfg: SceneConfig) -> dict[str, Any]:
    """Check the extra settings of ``cfg``; returns their normalized values (by key).

    Raises:
        SynthError: an unknown choice or a value out of range (the message names the key).
    """
    _choice(cfg, "animal", ANIMALS)
    _choice(cfg, "lens", LENSES)
    _choice(cfg, "layout", LAYOUTS)
    _choice(cfg, "floor", FLOORS)
    _choice(cfg, "walls", WALLS)
    _choice(cfg, "coat_mix", COAT_MIXES)
    out: dict[str, Any] = {}
    try:
        n = int(cfg.animals)
    except (TypeError, ValueError):
        n = 0
    if not 1 <= n <= MAX_ANIMALS or n != cfg.animals:
        raise SynthError(f"animals must be an integer in 1..{MAX_ANIMALS}, got {cfg.animals!r}")
    out["animals"] = n
    if cfg.animal_scales is not None:
        try:
            scales = tuple(float(v) for v in cfg.animal_scales)
        except (TypeError, ValueError):
            scales = ()
        if len(scales) != n or not all(0.3 <= v <= 1.5 for v in scales):
            raise SynthError(
                f"animal_scales must give one size factor in [0.3, 1.5] per animal ({n}), "
                f"got {cfg.animal_scales!r}"
            )
        out["animal_scales"] = scales
    for key, (lo, hi) in _RANGES.items():
        value = getattr(cfg, key)
        if value is None and key == "animal_scale":
            continue
        try:
            v = float(value)
        except (TypeError, ValueError):
            v = math.nan
        if not lo <= v <= hi:
            raise SynthError(f"{key} must be a number in [{lo}, {hi}], got {value!r}")
        out[key] = v
    gray = cfg.grayscale
    if not isinstance(gray, bool):
        if isinstance(gray, str) or not all(isinstance(n, str) for n in gray):
            raise SynthError(
                f"grayscale must be true/false or a list of camera names, got {gray!r}"
            )
        gray = tuple(gray)
    out["grayscale"] = gray
    formats = (cfg.label_files,) if isinstance(cfg.label_files, str) else tuple(cfg.label_files)
    bad = [f for f in formats if f not in LABEL_FORMATS]
    if bad:
        raise SynthError(
            f"label_files must list formats out of {', '.join(LABEL_FORMATS)}, got {bad!r}"
        )
    out["label_files"] = tuple(dict.fromkeys(formats))
    out["floor_color"] = _colour(cfg, "floor_color")
    out["wall_color"] = _colour(cfg, "wall_color")
    out["randomize"] = bool(cfg.randomize)
    return out


def body_scale(cfg: SceneConfig) -> float:
    """The animal's nominal size factor: ``animal_scale`` or the animal's (rat 1, mouse 0.42)."""
    return float(cfg.animal_scale) if cfg.animal_scale is not None else ANIMAL_SCALE[cfg.animal]


def is_grayscale(cfg: SceneConfig, camera: str) -> bool:
    """Whether camera ``camera`` of ``cfg`` records grayscale images."""
    g = cfg.grayscale
    return g if isinstance(g, bool) else camera in g


def scene_style(cfg: SceneConfig, camera: str) -> SceneStyle:
    """The photometric settings of camera ``camera`` in the scene ``cfg``."""
    return SceneStyle(
        grayscale=is_grayscale(cfg, camera),
        floor=cfg.floor,
        floor_color=cfg.floor_color,
        wall_color=cfg.wall_color,
        brightness=cfg.brightness,
        contrast=cfg.contrast,
        light_gradient=cfg.light_gradient,
        blur=cfg.blur,
        noise_level=cfg.noise_level,
        reflections=cfg.reflections,
        walls=cfg.walls,
    )


_SIZES = ((256, 208), (320, 256), (384, 304), (448, 352), (512, 416), (640, 512))


def _random_colour(rng: np.random.Generator, lo: float, hi: float) -> list[float]:
    """A mostly neutral colour of brightness in [lo, hi] with a small random tint (RGB)."""
    v = rng.uniform(lo, hi)
    tint = rng.normal(0.0, 0.06, size=3)
    return [float(np.clip(v * (1 + t), 0.0, 1.0)) for t in tint]


def randomized(cfg: SceneConfig, seed_value: int) -> SceneConfig:
    """``cfg`` with the domain-randomised settings drawn from ``seed_value``.

    Every drawn setting that ``cfg`` leaves at its default is replaced by the drawn value;
    settings given otherwise are kept (``SceneConfig(seed=S, randomize=True, size=(320,
    256))`` keeps the image size). Drawn (always all of them, in this order, so the same seed
    gives the same values whatever is kept): coat, body size
    (mouse to rat; ``animal`` follows the size), arena size and wall height (fitted to the
    animal), camera count 3-8, image size, rig layout, lens, grayscale, floor texture and
    colours, wall colour, brightness, contrast, light gradient, blur, noise level,
    reflections, resting and transparent walls. The frames, fps, stimulation, calibration
    video, label files and video format stay as given; with a ``rig_file`` the rig-related
    values are ignored.

    Returns:
        a config with ``randomize = False`` whose settings are all explicit (it renders the
        same scene, and its ``scene.toml`` reproduces it).
    """
    rng = np.random.default_rng(seed_value)
    coat = ("hooded", "albino", "dark")[int(rng.integers(3))]
    scale = float(math.exp(rng.uniform(math.log(0.4), math.log(1.12))))
    side = float(rng.uniform(2.4, 3.2) * 230.0 * scale)
    arena = (round(side, 1), round(side * float(rng.uniform(0.85, 1.15)), 1))
    wall = round(float(rng.uniform(0.12, 0.4)) * min(arena), 1)
    n_cameras = int(rng.integers(3, 9))
    size = _SIZES[int(rng.integers(len(_SIZES)))]
    layout = LAYOUTS[int(rng.choice(4, p=[0.4, 0.2, 0.2, 0.2]))]
    lens = LENSES[int(rng.choice(3, p=[0.5, 0.3, 0.2]))]
    gray = bool(rng.random() < 0.35)
    floor = FLOORS[int(rng.integers(2))]
    floor_color = _random_colour(rng, 0.15, 0.85)
    wall_color = _random_colour(rng, 0.3, 0.9)
    values: dict[str, Any] = {
        "appearance": coat,
        "animal": "mouse" if scale < 0.65 else "rat",
        "animal_scale": round(scale, 4),
        "arena_size": arena,
        "wall_height": wall,
        "n_cameras": n_cameras,
        "size": size,
        "layout": layout,
        "lens": lens,
        "grayscale": gray,
        "floor": floor,
        "floor_color": floor_color,
        "wall_color": wall_color,
        "brightness": round(float(rng.uniform(0.6, 1.4)), 4),
        "contrast": round(float(rng.uniform(0.7, 1.3)), 4),
        "light_gradient": round(float(rng.uniform(0.0, 0.5)), 4),
        "blur": round(float(rng.uniform(0.3, 1.5)) if rng.random() < 0.5 else 0.0, 4),
        "noise_level": round(float(math.exp(rng.uniform(math.log(0.3), math.log(3.0)))), 4),
        "reflections": round(float(rng.uniform(0.1, 0.4)) if rng.random() < 0.4 else 0.0, 4),
        "rest_fraction": round(float(rng.uniform(0.2, 0.7)) if rng.random() < 0.5 else 0.0, 4),
    }
    values["walls"] = WALLS[int(rng.random() < 0.3)]  # drawn last: earlier draws stay as they were
    defaults = {f.name: f.default for f in fields(cfg)}
    kept = {k: v for k, v in values.items() if getattr(cfg, k) == defaults[k]}
    return replace(cfg, **kept, randomize=False)


__all__ = [
    "ANIMALS",
    "ANIMAL_SCALE",
    "CONDITION_DEFAULTS",
    "FLOORS",
    "LABEL_FORMATS",
    "LAYOUTS",
    "LENSES",
    "WALLS",
    "body_scale",
    "check_conditions",
    "is_grayscale",
    "randomized",
    "scene_style",
]
