"""One camera's video of a synthetic session, rendered in a worker process."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from freipose.geometry import Camera, project
from freipose.synth.body import PART, BodyGeometry, per_animal_parts
from freipose.synth.look import SceneStyle
from freipose.synth.rig import ArenaConfig


def _blur_vectors(geom: BodyGeometry, cam: Camera, fps: float, shutter: float = 0.5) -> np.ndarray:
    """(T, 2) image motion of the torso during the exposure (``shutter`` of a frame).

    Several animals (their parts one after the other): the mean of their torsos' motions.
    """
    chests = per_animal_parts((PART["chest"],), geom.centers.shape[1])
    uv = project(geom.centers[:, chests], cam)  # (T, A, 2)
    if len(uv) < 2:
        return np.zeros((len(uv), 2))
    v = np.nan_to_num(np.gradient(uv, axis=0))
    return (v[:, 0] if len(chests) == 1 else v.mean(axis=1)) * shutter


@dataclass(frozen=True, eq=False)
class CameraJob:
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
        style: the scene's photometric settings for this camera.
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
    style: SceneStyle = field(default_factory=SceneStyle)


def render_camera(job: CameraJob) -> str:
    """Worker: render and write one camera's video (module level so it can be pickled)."""
    import cv2

    from freipose.io.video import VideoWriter
    from freipose.synth.render import CameraLook, CameraRenderer

    cv2.setNumThreads(1)
    cam, geom = job.camera, job.geometry
    look = CameraLook.random(np.random.default_rng(job.seed_look))
    if not job.noise:
        look = replace(look, noise_sigma=0.0)
    renderer = CameraRenderer(cam, job.arena, job.seed_look, look, job.style)
    rng = np.random.default_rng(job.seed_frames)
    vel = _blur_vectors(geom, cam, job.fps) if job.blur else np.zeros((len(geom), 2))
    with VideoWriter(job.path, job.fps, cam.size) as writer:
        for f in range(len(geom)):
            writer.write(renderer.render(geom, f, job.palette, rng, vel[f]))
    return str(job.path)


__all__ = ["CameraJob", "render_camera"]
