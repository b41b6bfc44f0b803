"""The settings of a synthetic session: :class:`SceneConfig` (``scene.toml``'s ``[scene]``).

:func:`freipose.synth.scene.generate_session` renders a session from it; every random
stream of the scene derives its seed from ``seed`` by :func:`derived_seed`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from freipose.io.toml import check_keys, read_toml
from freipose.synth.body import COATS
from freipose.synth.conditions import CONDITION_DEFAULTS, check_conditions, randomized
from freipose.synth.errors import SynthError
from freipose.synth.stimulation import StimulationConfig

VIDEO_FORMATS = (".mp4", ".mkv", ".avi")


def derived_seed(seed: int, *key: int) -> int:
    """A derived 63-bit seed for one random stream of the scene."""
    return int(np.random.SeedSequence([int(seed), *key]).generate_state(2, np.uint64)[0] >> 1)


@dataclass(frozen=True)
class SceneConfig:
    """Everything that defines a synthetic session (see ``generate_session``).

    Attributes:
        n_cameras: cameras of the default rig (ignored with ``rig_file``).
        rig_file: TOML rig file (see ``freipose.synth.rig``), or None for ``default_rig``.
        frames: number of frames.
        fps: frame rate.
        size: image size (width, height) of the default rig (and of rig-file cameras that
            give none).
        seed: the one seed everything random derives from.
        animal_seed: the seed the individual (body proportions, size within the animal's
            range, and the coat when ``appearance = "random"``) is drawn from; sessions with
            the same ``animal_seed`` film the same animal (another day of one rat). None: the
            session's ``seed``. With ``randomize`` the coat and the size class are drawn from
            ``seed`` with the other settings.
        appearance: ``"hooded"``, ``"albino"``, ``"dark"``, ``"piebald"`` (never drawn at
            random: a coat outside the shipped base models' training data) or ``"random"``
            (drawn from the seed).
        stimulation: stimulation protocol or None.
        calibration_video: also render the rig filming a calibration board.
        calibration_frames: frames of the calibration video.
        board: board description (``freipose.calibration.boards`` dict, with ``type``) or
            None for the default ChArUco board.
        video_format: ``".mp4"`` (small) or ``".mkv"`` (lossless FFV1, exact pixels).
        arena_size: inner arena (x, y) mm (ignored when the rig file has ``[arena]``).
        wall_height: arena wall height, mm.
        jitter_rig: jitter the default rig (positions, focal lengths, distortion) from the seed.
        motion_blur: directional motion blur of the animal.
        noise: sensor noise.
        animal: ``"rat"`` or ``"mouse"`` (a mouse is 0.42 times a rat's size; give it a
            smaller ``arena_size``, e.g. 250 x 250 mm).
        animal_scale: body size factor (rat = 1), None: the animal's.
        grayscale: every camera records grayscale (R = G = B; exact in lossless ``.mkv``,
            within a few grey levels after ``.mp4`` compression), or a tuple of the camera
            names that do (or ``grayscale = true`` per camera in a rig file).
        lens: ``"standard"`` (mild barrel distortion), ``"fisheye"`` (strong radial
            distortion, still monotonic in the image) or ``"pinhole"`` (none); default rig.
        layout: default rig layout: ``"ring"`` (around and above), ``"above"`` (all high
            up), ``"side"`` (low, over the walls), ``"below"`` (the last camera under a
            transparent floor, seeing the animal from below), ``"arc"`` (all on one side;
            never drawn by ``randomize``).
        reflections: reflectivity (0..0.9) of the walls: mirror images of the animal in
            them (the labels are of the real animal only).
        walls: ``"opaque"`` or ``"acrylic"``: transparent walls (an acrylic box) through
            which the cameras see the animal (keypoints behind them count as visible).
        rest_fraction: share of the time the animal rests (almost still for seconds).
        floor: ``"mat"`` or ``"bedding"`` (coarse grain texture).
        floor_color: floor colour, RGB 0..1 (None: the mat's grey, the bedding's beige).
        wall_color: wall colour, RGB 0..1 (None: light grey).
        brightness: exposure factor.
        contrast: contrast factor about mid grey.
        light_gradient: strength (0..0.9) of an illumination gradient across the image.
        blur: defocus blur of the whole image, Gaussian sigma in px.
        noise_level: factor on the sensor noise.
        label_files: also write per-camera label files of predicted instances as other
            tools do: ``"sleap"`` (``<camera>/<camera>.slp``), ``"dlc"``
            (``labeled-data/<session>_<camera>/CollectedData_synthetic.csv``); visible points
            only, with noise and a score.
        label_noise_px: standard deviation of the label files' 2D noise, px.
        animals: number of animals, 1..4 (2..4: a social scene, ``freipose.synth.social``:
            they meet, cross, climb over and hide each other; each is its own individual,
            drawn from ``animal_seed`` and its index).
        coat_mix: the coats of several animals with ``appearance = "random"``: ``random``
            (each drawn), ``same`` (all the first one's) or ``different`` (each another).
        animal_scales: one body size factor per animal (rat = 1), None: the animal's.
        randomize: domain randomisation: draw the coat, size, arena, cameras, image size,
            layout, lens, grayscale, floor, colours, lighting, blur, noise, reflections and
            resting from the seed (``freipose.synth.conditions.randomized``); the settings
            given other than at their defaults are kept.

    Call it as ``generate_session(OUT, SceneConfig(seed=S, randomize=True, frames=...))`` or
    ``freipose synth OUT --seed S --randomize``; ``SceneConfig(...).resolved()`` shows the
    drawn settings.
    """

    n_cameras: int = 7
    rig_file: str | None = None
    frames: int = 200
    fps: float = 50.0
    size: tuple[int, int] = (320, 256)
    seed: int = 0
    animal_seed: int | None = None
    appearance: str = "random"
    stimulation: StimulationConfig | None = None
    calibration_video: bool = False
    calibration_frames: int = 120
    board: Mapping[str, Any] | None = None
    video_format: str = ".mp4"
    arena_size: tuple[float, float] = (600.0, 600.0)
    wall_height: float = 100.0
    jitter_rig: bool = True
    motion_blur: bool = True
    noise: bool = True
    animal: str = "rat"
    animal_scale: float | None = None
    grayscale: bool | tuple[str, ...] = False
    lens: str = "standard"
    layout: str = "ring"
    reflections: float = 0.0
    walls: str = "opaque"
    rest_fraction: float = 0.0
    floor: str = "mat"
    floor_color: tuple[float, float, float] | None = None
    wall_color: tuple[float, float, float] | None = None
    brightness: float = 1.0
    contrast: float = 1.0
    light_gradient: float = 0.0
    blur: float = 0.0
    noise_level: float = 1.0
    label_files: tuple[str, ...] = ()
    label_noise_px: float = 1.0
    randomize: bool = False
    animals: int = 1
    coat_mix: str = "random"
    animal_scales: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if not 1 <= int(self.n_cameras) <= 32:
            raise SynthError(f"n_cameras must be in 1..32, got {self.n_cameras}")
        if int(self.frames) < 1:
            raise SynthError(f"frames must be >= 1, got {self.frames}")
        if not (0 < float(self.fps) <= 1000):
            raise SynthError(f"fps must be in (0, 1000], got {self.fps}")
        w, h = (int(v) for v in self.size)
        if w < 16 or h < 16 or w > 8192 or h > 8192:
            raise SynthError(f"size must be between 16x16 and 8192x8192 px, got {w}x{h}")
        if self.appearance not in (*COATS, "random"):
            raise SynthError(
                f"appearance must be hooded, albino, dark, piebald or random, "
                f"got {self.appearance!r}"
            )
        if self.video_format not in VIDEO_FORMATS:
            raise SynthError(
                f"video_format must be one of {VIDEO_FORMATS}, got {self.video_format!r}"
            )
        if int(self.calibration_frames) < 2:
            raise SynthError(f"calibration_frames must be >= 2, got {self.calibration_frames}")
        for name in ("seed", "animal_seed"):  # animal_seed may be unset (None)
            v = getattr(self, name)
            if (v is None and name == "seed") or (v is not None and not 0 <= int(v) < 2**63):
                raise SynthError(f"{name} must be a non-negative integer, got {v}")
            object.__setattr__(self, name, None if v is None else int(v))
        object.__setattr__(self, "size", (w, h))
        object.__setattr__(self, "n_cameras", int(self.n_cameras))
        object.__setattr__(self, "frames", int(self.frames))
        object.__setattr__(self, "fps", float(self.fps))
        object.__setattr__(self, "arena_size", tuple(float(v) for v in self.arena_size))
        if self.board is not None:
            object.__setattr__(self, "board", dict(self.board))
        for key, value in check_conditions(self).items():
            object.__setattr__(self, key, value)

    def resolved(self) -> SceneConfig:
        """The config with every setting explicit: with ``randomize``, the drawn settings."""
        return randomized(self, derived_seed(self.seed, 5)) if self.randomize else self

    # -- scene.toml ----------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Plain dict (TOML-serializable); ``from_dict`` inverts it."""
        d: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if v is None or (f.name in CONDITION_DEFAULTS and v == CONDITION_DEFAULTS[f.name]):
                continue
            if f.name == "stimulation":
                v = v.to_dict()
            elif isinstance(v, tuple):
                v = list(v)
            d[f.name] = v
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], source: str = "<dict>") -> SceneConfig:
        """The config of the plain dict ``d`` (as written by :meth:`to_dict`).

        Args:
            d: the settings (a ``[scene]`` table).
            source: where ``d`` comes from, for messages.

        Returns:
            The config.

        Raises:
            SynthError: an unknown or invalid setting.
        """
        check_keys(
            d, [f.name for f in fields(cls)], f"{source}: unknown scene settings", SynthError
        )
        kw = dict(d)
        if isinstance(kw.get("stimulation"), Mapping):
            kw["stimulation"] = StimulationConfig.from_dict(dict(kw["stimulation"]))
        for k in ("size", "arena_size", "floor_color", "wall_color", "label_files",
                  "animal_scales"):  # fmt: skip
            if k in kw and not isinstance(kw[k], str):
                kw[k] = tuple(kw[k])
        if isinstance(kw.get("grayscale"), list):
            kw["grayscale"] = tuple(kw["grayscale"])
        return cls(**kw)

    @classmethod
    def from_toml(cls, path: str | Path) -> SceneConfig:
        """Read the ``[scene]`` table of a ``scene.toml`` written by ``generate_session``.

        Args:
            path: the ``scene.toml``.

        Returns:
            The config.

        Raises:
            InputFileError: no such file.
            SynthError: not TOML, no ``[scene]`` table or an invalid setting.
        """
        data = read_toml(path, "scene file", SynthError)
        if "scene" not in data:
            raise SynthError(
                f"{path}: no [scene] table; is this a scene.toml written by freipose synth?"
            )
        return cls.from_dict(data["scene"], str(path))


__all__ = ["VIDEO_FORMATS", "SceneConfig", "derived_seed"]
