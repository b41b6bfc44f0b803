"""A whole synthetic session: :class:`SceneConfig` -> videos, calibration, labels, events.

Session folder written by :func:`generate_session` (formats in ``docs/formats.md``)::

    OUTDIR/<camera>.mp4        one video per camera (``.mkv``: lossless FFV1)
    OUTDIR/true_calibration.toml  the true cameras (the synthetic truth, not a calibration)
    OUTDIR/labels.h5           exact 3D keypoints, projections and visibility, every frame
    OUTDIR/events.csv          stimulation windows ``start_s,end_s`` (only when stimulated)
    OUTDIR/scene.toml          every parameter and the seed (reproduces the scene bit for bit)
    OUTDIR/<camera>/           with ``label_files`` sleap: <camera>.slp
    OUTDIR/labeled-data/       with ``label_files`` dlc: <session>_<camera>/CollectedData_*.csv
    OUTDIR/calibration/        with ``calibration_video``: board videos, board.toml,
                               true_calibration.toml (true rig), board_poses.npy

The same config (same seed) gives the same frames and labels; a run that was interrupted
resumes (videos already written completely are kept) when started again with the same config.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from freipose import __version__
from freipose.geometry import CameraRig
from freipose.io.atomic import atomic_write_text
from freipose.io.calibration import save_calibration
from freipose.io.session import TRUE_CALIBRATION_NAME
from freipose.io.toml import check_keys, read_toml
from freipose.synth.board import default_board, write_board_videos
from freipose.synth.body import (
    APPEARANCES,
    COATS,
    MOUSE_COATS,
    RAT_KEYPOINTS,
    BodyGeometry,
    RatBody,
    build_body,
)
from freipose.synth.camera_job import CameraJob, render_camera
from freipose.synth.conditions import (
    CONDITION_DEFAULTS,
    body_scale,
    check_conditions,
    randomized,
    scene_style,
)
from freipose.synth.errors import SynthError
from freipose.synth.label_files import check_label_formats
from freipose.synth.look import SceneStyle
from freipose.synth.motion import simulate_motion
from freipose.synth.rig import ArenaConfig, default_rig, grayscale_cameras, load_rig_file
from freipose.synth.stimulation import StimulationConfig
from freipose.workers import run_jobs

log = logging.getLogger(__name__)

VIDEO_FORMATS = (".mp4", ".mkv", ".avi")
# files of a session that --overwrite replaces (calibration.toml: older sessions' true rig)
_SESSION_FILES = (
    "labels.h5",
    "events.csv",
    "scene.toml",
    TRUE_CALIBRATION_NAME,
    "calibration.toml",
)


def _seed(seed: int, *key: int) -> int:
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
        return randomized(self, _seed(self.seed, 5)) if self.randomize else self

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
        for k in ("size", "arena_size", "floor_color", "wall_color", "label_files"):
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


@dataclass(frozen=True)
class SessionPaths:
    """The files of a generated session."""

    folder: Path
    videos: Mapping[str, Path]
    calibration: Path
    labels: Path
    scene: Path
    events: Path | None = None
    calibration_videos: Mapping[str, Path] = field(default_factory=dict)
    board: Path | None = None
    label_files: tuple[Path, ...] = ()


@dataclass(frozen=True, eq=False)
class Scene:
    """A fully resolved scene: rig, arena, animal, motion geometry (no pixels yet)."""

    config: SceneConfig
    rig: CameraRig
    arena: ArenaConfig
    body: RatBody
    geometry: BodyGeometry
    events: list[tuple[float, float]]


def resolve_rig(config: SceneConfig) -> tuple[CameraRig, ArenaConfig]:
    """The rig and arena of ``config`` (rig file or default rig)."""
    if config.rig_file is not None:
        rig, arena = load_rig_file(config.rig_file, default_size=config.size, with_arena=True)
        return rig, arena
    arena = ArenaConfig(config.arena_size, config.wall_height)
    seed = _seed(config.seed, 1) if config.jitter_rig else None
    rig = default_rig(
        config.n_cameras, config.size, seed=seed, arena=arena, lens=config.lens,
        layout=config.layout,
    )  # fmt: skip
    return rig, arena


def build_scene(config: SceneConfig) -> Scene:
    """Resolve the rig, draw the animal and simulate its motion (deterministic in the seed)."""
    config = config.resolved()
    if config.rig_file is not None and config.grayscale is False:
        gray = grayscale_cameras(config.rig_file)  # the rig file's monochrome cameras
        config = replace(config, grayscale=gray) if gray else config
    rig, arena = resolve_rig(config)
    coats = MOUSE_COATS if config.animal == "mouse" else APPEARANCES
    individual = config.seed if config.animal_seed is None else config.animal_seed
    body = RatBody.random(
        np.random.default_rng(_seed(individual, 2)), config.appearance, body_scale(config), coats
    )
    state = simulate_motion(
        config.frames, config.fps, np.random.default_rng(_seed(config.seed, 3)), body,
        config.stimulation, arena.size, rest_fraction=config.rest_fraction,
    )  # fmt: skip
    geom = build_body(body, state)
    events = config.stimulation.windows(config.frames / config.fps) if config.stimulation else []
    return Scene(config, rig, arena, body, geom, events)


def _scene_toml(config: SceneConfig, scene: Scene) -> str:
    b = scene.body
    doc: dict[str, Any] = {
        "freipose_version": __version__,
        "scene": config.to_dict(),
        "derived": {
            "note": "resolved from the seed (informational; not read back)",
            "cameras": list(scene.rig.names),
            "animal": {
                "appearance": b.appearance,
                "scale": b.scale,
                "length": b.length,
                "girth": b.girth,
                "tail_length": b.tail_length,
                "tint": list(b.tint),
            },  # fmt: skip
            "arena": {"size": list(scene.arena.size), "wall_height": scene.arena.wall_height},
        },
    }
    if config.rig_file is not None:
        doc["derived"]["rig_file_text"] = Path(config.rig_file).read_text(encoding="utf-8")
    return tomli_w.dumps(doc)


def _occluding_walls(scene: Scene) -> ArenaConfig:
    """The arena as the visibility test sees it: transparent walls hide nothing."""
    if scene.config.walls == "acrylic":
        return ArenaConfig(scene.arena.size, 0.0)
    return scene.arena


def write_labels(scene: Scene, folder: Path, session: str) -> Path:
    """Compute projections and visibility and write ``labels.h5`` for every frame."""
    from freipose.io.labels import LabelSet, SessionInfo, write_labels_h5
    from freipose.synth.visibility import keypoint_visibility

    cfg = scene.config
    pts2d, vis = keypoint_visibility(scene.geometry, scene.rig, _occluding_walls(scene))
    T = len(scene.geometry)
    videos = {c: f"{c}{cfg.video_format}" for c in scene.rig.names}
    labels = LabelSet(
        session=np.array([session] * T, dtype=object),
        frame_index=np.arange(T),
        points2d=pts2d,
        points3d=scene.geometry.keypoints,
        cameras=tuple(scene.rig.names),
        keypoints=RAT_KEYPOINTS,
        sessions={session: SessionInfo(scene.rig, videos, cfg.fps)},
        visible2d=vis,
    )
    path = folder / "labels.h5"
    write_labels_h5(labels, path)
    return path


def _prepare_folder(out: Path, scene_text: str, overwrite: bool) -> None:
    """Make ``out`` ready for the scene whose ``scene.toml`` is ``scene_text``.

    A folder holding the same scene is kept as it is (resume); the files of a different
    scene are deleted with ``overwrite``.

    Raises:
        SynthError: ``out`` is a file, or holds another scene or unrelated files (and not
            ``overwrite``).
    """
    scene_path = out / "scene.toml"
    if out.exists() and not out.is_dir():
        raise SynthError(f"{out} exists and is not a folder; choose another output folder")
    if out.is_dir() and any(out.iterdir()):
        same = scene_path.is_file() and scene_path.read_text(encoding="utf-8") == scene_text
        if not same and not overwrite:
            what = "a different scene" if scene_path.is_file() else "other files"
            raise SynthError(
                f"{out} already holds {what}; pass overwrite=True (--overwrite) to replace it, "
                "or choose an empty folder"
            )
        if not same:
            for p in [*out.glob("*/*.slp"), *out.glob("labeled-data/*/CollectedData_*.csv")]:
                p.unlink()
            for p in out.glob("*"):
                if p.is_file() and (p.suffix in VIDEO_FORMATS or p.name in _SESSION_FILES):
                    p.unlink()
    out.mkdir(parents=True, exist_ok=True)


def _write_label_files(scene: Scene, out: Path, videos: Mapping[str, Path]) -> tuple[Path, ...]:
    """Write the per-camera label files of ``label_files`` (``freipose.synth.label_files``)."""
    from freipose.synth.label_files import noisy_labels, write_label_files
    from freipose.synth.visibility import keypoint_visibility

    cfg = scene.config
    if not cfg.label_files:
        return ()
    pts2d, vis = keypoint_visibility(scene.geometry, scene.rig, _occluding_walls(scene))
    rng = np.random.default_rng(_seed(cfg.seed, 6))
    noisy = noisy_labels(pts2d, vis, cfg.label_noise_px, rng)
    session = out.resolve().name
    files = write_label_files(out, session, cfg.label_files, dict(videos), RAT_KEYPOINTS, noisy)
    return tuple(files)


def _write_events(scene: Scene, out: Path) -> Path | None:
    """Write ``events.csv`` (the stimulation windows) when the scene is stimulated."""
    config = scene.config
    if config.stimulation is None:
        return None
    events_path = out / "events.csv"
    lines = ["start_s,end_s"] + [f"{a:.6f},{b:.6f}" for a, b in scene.events]
    atomic_write_text(events_path, "\n".join(lines) + "\n")
    if not scene.events:
        log.warning(
            "no stimulation window fits into %.2f s; events.csv is empty",
            config.frames / config.fps,
        )
    return events_path


def _render_videos(
    scene: Scene, videos: Mapping[str, Path], workers: int | None, progress: bool | None
) -> int:
    """Render the cameras' videos not yet in place; returns the number of workers used."""
    config = scene.config
    palette = scene.body.palette
    jobs = []
    for i, cam in enumerate(scene.rig):
        if videos[cam.name].is_file():
            log.info("keeping %s (already rendered for this scene)", videos[cam.name])
            continue
        jobs.append(
            CameraJob(
                camera=cam,
                arena=scene.arena,
                geometry=scene.geometry,
                palette=palette,
                path=videos[cam.name],
                fps=config.fps,
                seed_look=_seed(config.seed, 100 + i),
                seed_frames=_seed(config.seed, 200 + i),
                blur=config.motion_blur,
                noise=config.noise,
                style=scene_style(config, cam.name),
            )
        )
    if workers is None:  # processes only pay off for big jobs (each one starts Python anew)
        pixels = config.frames * len(scene.rig) * config.size[0] * config.size[1]
        workers = min(2, os.cpu_count() or 1) if pixels > 2e7 else 1
    n_workers = min(len(jobs), workers)
    run_jobs(render_camera, jobs, n_workers, "render cameras", progress)
    return n_workers


def _write_calibration_video(
    scene: Scene, out: Path, workers: int, progress: bool | None
) -> tuple[dict[str, Path], Path]:
    """Film the board into ``out/calibration`` (double-sided if a camera is under the floor)."""
    config = scene.config
    board = default_board(scene.arena) if config.board is None else _board_from(config.board)
    cal_videos, _ = write_board_videos(
        out / "calibration",
        scene.rig,
        board,
        config.calibration_frames,
        _seed(config.seed, 4),
        fps=config.fps,
        fmt=config.video_format,
        arena=scene.arena,
        workers=workers,
        progress=progress,
        styles=_board_styles(config, scene.rig),
        transparent=any(c.center[2] < 0 for c in scene.rig),
    )
    return cal_videos, out / "calibration" / "board.toml"


def _board_styles(config: SceneConfig, rig: CameraRig) -> dict[str, SceneStyle] | None:
    """The cameras' photometric settings for the board videos (None: all the classic ones).

    The walls' reflections are left out (the board's mirror images are not rendered).
    """
    styles = {c.name: replace(scene_style(config, c.name), reflections=0.0) for c in rig}
    return None if all(st == SceneStyle() for st in styles.values()) else styles


def generate_session(
    outdir: str | Path,
    config: SceneConfig | None = None,
    workers: int | None = None,
    overwrite: bool = False,
    progress: bool | None = None,
) -> SessionPaths:
    """Render a synthetic session into ``outdir`` (layout in the module docstring).

    Args:
        outdir: output folder (created; the session name is its name).
        config: the scene (default ``SceneConfig()``).
        workers: processes rendering cameras in parallel (default: up to 2, one per camera);
            the output does not depend on it.
        overwrite: replace a different scene already in ``outdir``.
        progress: show progress bars (None: only on a terminal).

    Returns:
        :class:`SessionPaths`.

    Raises:
        SynthError: ``outdir`` holds another scene or unrelated files (and not ``overwrite``).
    """
    out = Path(outdir)
    scene = build_scene(config or SceneConfig())
    config = scene.config  # resolved: with randomize, the drawn settings
    text = _scene_toml(config, scene)
    scene_path = out / "scene.toml"
    check_label_formats(config.label_files)  # a missing extra: nothing written
    _prepare_folder(out, text, overwrite)
    atomic_write_text(scene_path, text)
    session = out.resolve().name
    save_calibration(scene.rig, out / TRUE_CALIBRATION_NAME)
    events_path = _write_events(scene, out)
    labels_path = write_labels(scene, out, session)
    videos = {c.name: out / f"{c.name}{config.video_format}" for c in scene.rig}
    label_files = _write_label_files(scene, out, videos)
    n_workers = _render_videos(scene, videos, workers, progress)
    cal_videos: dict[str, Path] = {}
    board_path = None
    if config.calibration_video:
        cal_videos, board_path = _write_calibration_video(scene, out, n_workers or 1, progress)
    return SessionPaths(out, videos, out / TRUE_CALIBRATION_NAME, labels_path, scene_path,
                        events_path, cal_videos, board_path, label_files)  # fmt: skip


def _board_from(d: Mapping[str, Any]) -> Any:
    """The calibration board described by the dict ``d`` (``freipose.calibration.boards``)."""
    from freipose.calibration.board_files import board_from_dict

    return board_from_dict(dict(d), "scene board")


__all__ = [
    "SceneConfig",
    "SessionPaths",
    "Scene",
    "build_scene",
    "generate_session",
    "resolve_rig",
    "write_labels",
]
