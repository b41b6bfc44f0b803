"""Render speed of ``freipose synth``: frames per second per camera on one CPU core.

Measures, in one run:

* the per-camera renderer (culled inverse mapping: only the pixels inside the projected
  bounding box of each body part are ray-cast) at each ``--sizes``, with and without video
  encoding, against a brute-force baseline measured in the same run (every pixel against
  every part, no culling; same images);
* the one-off per-camera set-up (pixel rays with exact undistortion, static background);
* the calibration-board renderer (3 x 3 anti-aliased, exact with distortion);
* the renderer under the conditions of real rigs (``SceneConfig`` keys: a mouse, fisheye
  lenses, grayscale, reflective walls, bedding) and of randomised scenes, against the classic
  scene at the same image size;
* optionally (``--session``) the wall time of a whole 7-camera, 200-frame session with
  ``generate_session`` and 2 worker processes (the demo scale).

Example::

    python benchmarks/synth.py --sizes 640x512,320x256 --frames 100 --session
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from _results import write_result  # noqa: E402

if TYPE_CHECKING:
    from freipose.synth.body import BodyGeometry
    from freipose.synth.render import CameraRenderer


def _brute_force_ids(r: CameraRenderer, geom: BodyGeometry, f: int) -> np.ndarray:
    """Baseline: every pixel of the image against every ellipsoid (no culling); part ids."""
    C, A, Rr = geom.centers[f], geom.axes[f], geom.radii[f]
    Dx, Dy, Dz = r.rays_soa
    z = r.bg_depth.copy()
    pid = np.full(z.shape, -1)
    for i in range(len(C)):
        M = A[i] / Rr[i]
        op = (r.origin - C[i]) @ M
        dpx = M[0, 0] * Dx + M[1, 0] * Dy + M[2, 0] * Dz
        dpy = M[0, 1] * Dx + M[1, 1] * Dy + M[2, 1] * Dz
        dpz = M[0, 2] * Dx + M[1, 2] * Dy + M[2, 2] * Dz
        a = dpx * dpx + dpy * dpy + dpz * dpz
        b = dpx * op[0] + dpy * op[1] + dpz * op[2]
        disc = b * b - a * (op @ op - 1)
        s = (-b - np.sqrt(np.maximum(disc, 0))) / a
        upd = (disc > 0) & (s > 0) & (s < z)
        z[upd] = s[upd]
        pid[upd] = i
    return pid


def bench_size(size: tuple[int, int], frames: int) -> dict[str, float]:
    from freipose.io.video import VideoWriter
    from freipose.synth import SceneConfig
    from freipose.synth.camera_job import _blur_vectors
    from freipose.synth.render import CameraRenderer
    from freipose.synth.scene import build_scene

    scene = build_scene(SceneConfig(frames=max(frames, 10), size=size, seed=0))
    geom, pal = scene.geometry, scene.body.palette
    cam = scene.rig[0]
    t0 = time.process_time()
    r = CameraRenderer(cam, scene.arena, seed=1)
    setup = time.process_time() - t0
    vel = _blur_vectors(geom, cam, scene.config.fps)
    rng = np.random.default_rng(0)
    t0 = time.process_time()
    for f in range(frames):
        r.render(geom, f, pal, rng, vel[f])
    render_s = (time.process_time() - t0) / frames
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.process_time()
        with VideoWriter(Path(tmp) / "c.mp4", 50, cam.size) as w:
            for f in range(frames):
                w.write(r.render(geom, f, pal, rng, vel[f]))
        encode_s = (time.process_time() - t0) / frames
    n_base = 3
    t0 = time.process_time()
    for f in range(n_base):
        ids = _brute_force_ids(r, geom, f)
    base_s = (time.process_time() - t0) / n_base
    # the culled renderer finds the same pixels as the brute force
    (x0, y0, x1, y1), _, pid = r.render_animal(geom, n_base - 1, pal)
    full = np.full(ids.shape, -1)
    full[y0:y1, x0:x1] = pid
    differ = int((full != ids).sum())  # grazing-ray pixels (float32 vs float64) only
    animal = int((ids >= 0).sum())
    w, h = size
    per_cam = "frames/s per camera"
    est = 7 * (200 * encode_s + setup)
    print(f"{w}x{h}, camera {cam.name}, {frames} frames (CPU time, 1 core):")
    print(f"  set-up (rays, background)    {setup:8.3f} s per camera, once")
    print(f"  render                       {1 / render_s:8.1f} {per_cam} ({render_s * 1e3:.1f} ms)")
    print(f"  render + mp4 encoding        {1 / encode_s:8.1f} {per_cam} ({encode_s * 1e3:.1f} ms)")
    print(f"  baseline: brute-force rays   {1 / base_s:8.2f} {per_cam} (ray casting only)")
    print(f"  speed-up over the baseline   {base_s / render_s:8.1f} x")
    print(f"  part ids differing from it   {differ:8d} of {animal} animal pixels (grazing rays)")
    print(f"  7-camera 200-frame scene     {est:8.1f} s CPU on one core (estimate)")
    return {
        "setup_s": setup,
        "render_fps": 1 / render_s,
        "render_encode_fps": 1 / encode_s,
        "brute_force_fps": 1 / base_s,
        "speedup": base_s / render_s,
        "part_ids_differing": differ,
        "session_7cam_200f_cpu_s": est,
    }


def bench_board(size: tuple[int, int], frames: int) -> dict[str, float]:
    from freipose.synth import board_poses, default_board, default_rig
    from freipose.synth.board import _auto_ppm, _BoardTexture, _iter_board_camera

    rig = default_rig(1, size, seed=0)
    board = default_board()
    t0 = time.process_time()
    tex = _BoardTexture(board, _auto_ppm(rig), None)
    tex_s = time.process_time() - t0
    poses = board_poses(frames, (600, 600), 0, board.size_mm)
    t0 = time.process_time()
    n = sum(1 for _ in _iter_board_camera(rig[0], 0, tex, poses, 0, True, True, None))
    per = (time.process_time() - t0) / n
    print(f"board {size[0]}x{size[1]}: {1 / per:.1f} frames/s per camera incl. set-up "
          f"({per * 1e3:.1f} ms); board texture {tex_s:.2f} s once")  # fmt: skip
    return {"board_fps": 1 / per, "board_texture_s": tex_s}


def bench_conditions(size: tuple[int, int], frames: int) -> dict[str, float]:
    from freipose.synth import SceneConfig
    from freipose.synth.camera_job import _blur_vectors
    from freipose.synth.conditions import scene_style
    from freipose.synth.render import CameraRenderer
    from freipose.synth.scene import build_scene

    n = max(frames, 10)
    lab = dict(animal="mouse", arena_size=(250.0, 250.0), wall_height=120.0, lens="fisheye",
               grayscale=True, reflections=0.3, floor="bedding")  # fmt: skip
    configs = {
        "classic scene": SceneConfig(frames=n, size=size, seed=0),
        "lab rig: mouse, fisheye, grayscale, reflections, bedding": SceneConfig(
            frames=n, size=size, seed=0, **lab
        ),
        **{
            f"randomized, seed {s}": SceneConfig(frames=n, size=size, seed=s, randomize=True)
            for s in (1, 2, 3)
        },  # fmt: skip
    }
    print(f"{size[0]}x{size[1]}, camera 0, {frames} frames, by scene (CPU time, 1 core):")
    fps = {}
    for name, cfg in configs.items():
        scene = build_scene(cfg)
        cam = scene.rig[0]
        t0 = time.process_time()
        r = CameraRenderer(cam, scene.arena, seed=1, style=scene_style(scene.config, cam.name))
        setup = time.process_time() - t0
        vel = _blur_vectors(scene.geometry, cam, cfg.fps)
        rng = np.random.default_rng(0)
        t0 = time.process_time()
        for f in range(frames):
            r.render(scene.geometry, f, scene.body.palette, rng, vel[f])
        per = (time.process_time() - t0) / frames
        print(f"  {name:58s} {1 / per:7.1f} frames/s ({per * 1e3:.1f} ms), set-up {setup:.2f} s")
        fps[name.split(":")[0]] = 1 / per
    return fps


def bench_session(size: tuple[int, int]) -> float:
    from freipose.synth import SceneConfig, generate_session

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        generate_session(Path(tmp) / "s", SceneConfig(frames=200, size=size, seed=0), workers=2,
                         progress=False)  # fmt: skip
        wall = time.perf_counter() - t0
    print(f"session 7 cameras x 200 frames {size[0]}x{size[1]}, 2 workers: {wall:.1f} s wall")
    return wall


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="640x512,320x256")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--session", action="store_true", help="also time whole 7-camera sessions")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    figures: dict[str, object] = {}
    for w, h in sizes:
        figures[f"{w}x{h}"] = bench_size((w, h), args.frames)
    figures[f"board {sizes[0][0]}x{sizes[0][1]}"] = bench_board(sizes[0], 20)
    figures[f"fps by scene {sizes[-1][0]}x{sizes[-1][1]}"] = bench_conditions(
        sizes[-1], args.frames
    )
    if args.session:
        for w, h in sizes:
            figures[f"{w}x{h}"]["session_2_workers_wall_s"] = bench_session((w, h))
    write_result("synth", figures, extra={"frames": args.frames, "sizes": args.sizes})


if __name__ == "__main__":
    main()
