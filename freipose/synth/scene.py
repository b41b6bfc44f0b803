"""A whole synthetic session: :class:`SceneConfig` -> videos, calibration, labels, events.

Session folder written by :func:`generate_session` (formats in ``docs/formats.md``)::

    OUTDIR/<camera>.mp4        one video per camera (``.mkv``: lossless FFV1)
    OUTDIR/true_calibration.toml  the true cameras (the synthetic truth, not a calibration)
    OUTDIR/labels.h5           exact 3D keypoints, projections and visibility, every frame
                               (several animals: one row per frame and animal, ``individual``)
    OUTDIR/true_poses.h5       several animals: the truth as a poses file (T, A, K, 3)
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
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from freipose import __version__
from freipose.geometry import CameraRig
from freipose.io.atomic import atomic_write_text
from freipose.io.calibration import save_calibration
from freipose.io.session import TRUE_CALIBRATION_NAME
from freipose.synth.board import default_board, write_board_videos
from freipose.synth.body import (
    APPEARANCES,
    MOUSE_COATS,
    RAT_KEYPOINTS,
    BodyGeometry,
    RatBody,
    build_body,
)
from freipose.synth.camera_job import CameraJob, render_camera
from freipose.synth.conditions import (
    body_scale,
    scene_style,
)
from freipose.synth.config import VIDEO_FORMATS, SceneConfig, derived_seed
from freipose.synth.errors import SynthError
from freipose.synth.label_files import check_label_formats
from freipose.synth.look import SceneStyle
from freipose.synth.motion import simulate_motion
from freipose.synth.rig import ArenaConfig, default_rig, grayscale_cameras, load_rig_file
from freipose.synth.social import (
    SocialMotion,
    combine_geometries,
    combined_palette,
    simulate_social,
)
from freipose.synth.social_scene import (
    TRUE_POSES_NAME,
    animal_names,
    social_bodies,
    write_social_labels,
)
from freipose.workers import run_jobs

log = logging.getLogger(__name__)
_seed = derived_seed

# files of a session that --overwrite replaces (calibration.toml: older sessions' true rig)
_SESSION_FILES = (
    "labels.h5",
    TRUE_POSES_NAME,
    "config.yaml",
    "events.csv",
    "scene.toml",
    TRUE_CALIBRATION_NAME,
    "calibration.toml",
)


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
    truth: Path | None = None  # several animals: true_poses.h5


@dataclass(frozen=True, eq=False)
class Scene:
    """A fully resolved scene: rig, arena, animal, motion geometry (no pixels yet)."""

    config: SceneConfig
    rig: CameraRig
    arena: ArenaConfig
    body: RatBody
    geometry: BodyGeometry
    events: list[tuple[float, float]]
    bodies: tuple[RatBody, ...] = ()
    social: SocialMotion | None = None

    @property
    def n_animals(self) -> int:
        """The number of animals A."""
        return max(1, len(self.bodies))

    @property
    def individuals(self) -> tuple[str, ...]:
        """(A,) the animals' names, ``animal0``, ``animal1``, ..."""
        return animal_names(self.n_animals)

    @property
    def palette(self) -> np.ndarray:
        """(A * M, 2, 3) the colours of the geometry's materials (every animal's coat)."""
        return combined_palette(self.bodies) if self.social is not None else self.body.palette


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
    if config.animals > 1:
        return _social_scene(config, rig, arena)
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


def _social_scene(config: SceneConfig, rig: CameraRig, arena: ArenaConfig) -> Scene:
    """The scene of several animals (``freipose.synth.social``)."""
    individual = config.seed if config.animal_seed is None else config.animal_seed
    seeds = [
        _seed(individual, 2) if a == 0 else _seed(individual, 2, a) for a in range(config.animals)
    ]
    scales = config.animal_scales or (body_scale(config),) * config.animals
    bodies = social_bodies(config.animal, config.appearance, config.coat_mix, scales, seeds)
    rngs = [np.random.default_rng(_seed(config.seed, 3, a)) for a in range(len(bodies))]
    motion = simulate_social(
        config.frames, config.fps, rngs, np.random.default_rng(_seed(config.seed, 7)), bodies,
        arena.size, config.stimulation, config.rest_fraction,
    )  # fmt: skip
    geoms = [build_body(b, st) for b, st in zip(bodies, motion.states)]
    geom = combine_geometries(geoms, motion.lift)
    events = config.stimulation.windows(config.frames / config.fps) if config.stimulation else []
    return Scene(config, rig, arena, bodies[0], geom, events, bodies, motion)


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
    if scene.social is not None:
        doc["derived"]["animals"] = [
            {"name": name, "appearance": a.appearance, "scale": a.scale, "length": a.length,
             "girth": a.girth, "tail_length": a.tail_length, "tint": list(a.tint)}
            for name, a in zip(scene.individuals, scene.bodies)
        ]  # fmt: skip
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
    if scene.social is not None:
        labels_path = folder / "labels.h5"
        write_social_labels(labels_path, folder / TRUE_POSES_NAME, session, scene.rig,
                            scene.geometry, scene.social, _occluding_walls(scene),
                            cfg.fps, cfg.video_format)  # fmt: skip
        return labels_path
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
            old = [*out.glob("*.slp"), *out.glob("*/*.slp")]
            for p in [*old, *out.glob("labeled-data/*/CollectedData_*.csv")]:
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
    individuals = scene.individuals if scene.social is not None else None
    files = write_label_files(
        out, session, cfg.label_files, dict(videos), RAT_KEYPOINTS, noisy, individuals, scene.rig
    )
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
    palette = scene.palette
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
    truth = out / TRUE_POSES_NAME if scene.social is not None else None
    return SessionPaths(out, videos, out / TRUE_CALIBRATION_NAME, labels_path, scene_path,
                        events_path, cal_videos, board_path, label_files, truth)  # fmt: skip


def _board_from(d: Mapping[str, Any]) -> Any:
    """The calibration board described by the dict ``d`` (``freipose.calibration.boards``)."""
    from freipose.calibration.board_files import board_from_dict

    return board_from_dict(dict(d), "scene board")


__all__ = [
    "SceneConfig",
    "SessionPaths",
    "Scene",
    "TRUE_POSES_NAME",
    "build_scene",
    "generate_session",
    "resolve_rig",
    "write_labels",
]
