"""A whole synthetic session: :class:`SceneConfig` -> videos, calibration, labels, events.

Session folder written by :func:`generate_session` (formats in ``docs/formats.md``)::

    OUTDIR/<camera>.mp4        one video per camera (``.mkv``: lossless FFV1)
    OUTDIR/calibration.toml    the true cameras
    OUTDIR/labels.h5           exact 3D keypoints, projections and visibility, every frame
    OUTDIR/events.csv          stimulation windows ``start_s,end_s`` (only when stimulated)
    OUTDIR/scene.toml          every parameter and the seed (reproduces the scene bit for bit)
    OUTDIR/calibration/        with ``calibration_video``: board videos, board.toml,
                               calibration.toml (true rig), board_poses.npy

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
from freipose.geometry import Camera, CameraRig, project
from freipose.io.atomic import atomic_write_text
from freipose.io.calibration import save_calibration
from freipose.io.toml import check_keys, read_toml
from freipose.synth.board import default_board, write_board_videos
from freipose.synth.body import APPEARANCES, PART, RAT_KEYPOINTS, BodyGeometry, RatBody, build_body
from freipose.synth.errors import SynthError
from freipose.synth.motion import simulate_motion
from freipose.synth.rig import ArenaConfig, default_rig, load_rig_file
from freipose.synth.stimulation import StimulationConfig
from freipose.workers import run_jobs

log = logging.getLogger(__name__)

VIDEO_FORMATS = (".mp4", ".mkv", ".avi")


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
        appearance: ``"hooded"``, ``"albino"`` or ``"random"`` (drawn from the seed).
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
    """

    n_cameras: int = 7
    rig_file: str | None = None
    frames: int = 200
    fps: float = 50.0
    size: tuple[int, int] = (320, 256)
    seed: int = 0
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
        if self.appearance not in (*APPEARANCES, "random"):
            raise SynthError(
                f"appearance must be hooded, albino or random, got {self.appearance!r}"
            )
        if self.video_format not in VIDEO_FORMATS:
            raise SynthError(
                f"video_format must be one of {VIDEO_FORMATS}, got {self.video_format!r}"
            )
        if int(self.calibration_frames) < 2:
            raise SynthError(f"calibration_frames must be >= 2, got {self.calibration_frames}")
        if not 0 <= int(self.seed) < 2**63:
            raise SynthError(f"seed must be a non-negative integer, got {self.seed}")
        object.__setattr__(self, "size", (w, h))
        object.__setattr__(self, "n_cameras", int(self.n_cameras))
        object.__setattr__(self, "frames", int(self.frames))
        object.__setattr__(self, "fps", float(self.fps))
        object.__setattr__(self, "seed", int(self.seed))
        object.__setattr__(self, "arena_size", tuple(float(v) for v in self.arena_size))
        if self.board is not None:
            object.__setattr__(self, "board", dict(self.board))

    # -- scene.toml ----------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Plain dict (TOML-serializable); ``from_dict`` inverts it."""
        d: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if v is None:
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
        for k in ("size", "arena_size"):
            if k in kw:
                kw[k] = tuple(kw[k])
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
    return default_rig(config.n_cameras, config.size, seed=seed, arena=arena), arena


def build_scene(config: SceneConfig) -> Scene:
    """Resolve the rig, draw the animal and simulate its motion (deterministic in the seed)."""
    rig, arena = resolve_rig(config)
    body = RatBody.random(np.random.default_rng(_seed(config.seed, 2)), config.appearance)
    state = simulate_motion(
        config.frames, config.fps, np.random.default_rng(_seed(config.seed, 3)), body,
        config.stimulation, arena.size,
    )  # fmt: skip
    geom = build_body(body, state)
    events = config.stimulation.windows(config.frames / config.fps) if config.stimulation else []
    return Scene(config, rig, arena, body, geom, events)


def _blur_vectors(geom: BodyGeometry, cam: Camera, fps: float, shutter: float = 0.5) -> np.ndarray:
    """(T, 2) image motion of the torso during the exposure (``shutter`` of a frame)."""
    uv = project(geom.centers[:, PART["chest"]], cam)
    if len(uv) < 2:
        return np.zeros((len(uv), 2))
    v = np.gradient(uv, axis=0)
    return np.nan_to_num(v) * shutter


@dataclass(frozen=True, eq=False)
class _CameraJob:
    """What a worker needs to render one camera's video.

    Attributes:
        camera: the camera.
        arena: the arena.
        geometry: the animal over all frames.
        palette: (n_materials, 2, 3) BGR albedo of the animal.
        path: the video file to write.
        fps: frame rate.
        seed_look: seed of the camera's look and textures.
        seed_frames: seed of the per-frame sensor noise.
        blur: motion blur.
        noise: sensor noise.
    """

    camera: Camera
    arena: ArenaConfig
    geometry: BodyGeometry
    palette: np.ndarray
    path: Path
    fps: float
    seed_look: int
    seed_frames: int
    blur: bool
    noise: bool


def _render_camera(job: _CameraJob) -> str:
    """Worker: render and write one camera's video (module level so it can be pickled)."""
    import cv2

    from freipose.io.video import VideoWriter
    from freipose.synth.render import CameraLook, CameraRenderer

    cv2.setNumThreads(1)
    cam, geom = job.camera, job.geometry
    look = CameraLook.random(np.random.default_rng(job.seed_look))
    if not job.noise:
        look = replace(look, noise_sigma=0.0)
    renderer = CameraRenderer(cam, job.arena, job.seed_look, look)
    rng = np.random.default_rng(job.seed_frames)
    vel = _blur_vectors(geom, cam, job.fps) if job.blur else np.zeros((len(geom), 2))
    with VideoWriter(job.path, job.fps, cam.size) as writer:
        for f in range(len(geom)):
            writer.write(renderer.render(geom, f, job.palette, rng, vel[f]))
    return str(job.path)


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


def write_labels(scene: Scene, folder: Path, session: str) -> Path:
    """Compute projections and visibility and write ``labels.h5`` for every frame."""
    from freipose.io.labels import LabelSet, SessionInfo, write_labels_h5
    from freipose.synth.visibility import keypoint_visibility

    cfg = scene.config
    pts2d, vis = keypoint_visibility(scene.geometry, scene.rig, scene.arena)
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
            for p in out.glob("*"):
                if p.is_file() and (
                    p.suffix in VIDEO_FORMATS
                    or p.name in ("labels.h5", "events.csv", "scene.toml", "calibration.toml")
                ):
                    p.unlink()
    out.mkdir(parents=True, exist_ok=True)


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
            _CameraJob(
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
            )
        )
    if workers is None:  # processes only pay off for big jobs (each one starts Python anew)
        pixels = config.frames * len(scene.rig) * config.size[0] * config.size[1]
        workers = min(2, os.cpu_count() or 1) if pixels > 2e7 else 1
    n_workers = min(len(jobs), workers)
    run_jobs(_render_camera, jobs, n_workers, "render cameras", progress)
    return n_workers


def _write_calibration_video(
    scene: Scene, out: Path, workers: int, progress: bool | None
) -> tuple[dict[str, Path], Path]:
    """Render the rig filming the board into ``out/calibration``: (videos, board.toml)."""
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
    )
    return cal_videos, out / "calibration" / "board.toml"


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
    config = config or SceneConfig()
    out = Path(outdir)
    scene = build_scene(config)
    text = _scene_toml(config, scene)
    scene_path = out / "scene.toml"
    _prepare_folder(out, text, overwrite)
    atomic_write_text(scene_path, text)
    session = out.resolve().name
    save_calibration(scene.rig, out / "calibration.toml")
    events_path = _write_events(scene, out)
    labels_path = write_labels(scene, out, session)
    videos = {c.name: out / f"{c.name}{config.video_format}" for c in scene.rig}
    n_workers = _render_videos(scene, videos, workers, progress)
    cal_videos: dict[str, Path] = {}
    board_path = None
    if config.calibration_video:
        cal_videos, board_path = _write_calibration_video(scene, out, n_workers or 1, progress)
    return SessionPaths(out, videos, out / "calibration.toml", labels_path, scene_path,
                        events_path, cal_videos, board_path)  # fmt: skip


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
