"""Synthetic calibration videos: the rig filming a calibration board waved through the arena.

The board (any ``freipose.calibration.boards`` board, or anything with ``size_mm`` and
``texture(px_per_mm)``) is a plane rendered exactly by inverse mapping: each pixel's
(distortion-exact) viewing ray is intersected with the board plane, 3 x 3 sub-pixel rays
are averaged (anti-aliasing; sub-pixel rays from the per-pixel ray field's derivatives) and
the printed texture is looked up at the hit points. The printed pattern sits on a white
substrate with a margin; its back side is grey, or, for a transparent (or double-sided) print,
the pattern seen from behind: mirrored. A camera below the floor (z < 0) looks through it, as
through a glass or acrylic floor.

Board frame (shared with the calibration code): z = 0 is the board plane, x along the
texture columns, y along its rows, origin at the texture's top-left pixel edge; the printed
side faces -z. A pose is the 4 x 4 board->world transform.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from freipose.geometry import Camera, CameraRig, project
from freipose.synth.errors import SynthError
from freipose.synth.look import SceneStyle
from freipose.synth.rig import ArenaConfig
from freipose.workers import run_jobs

if TYPE_CHECKING:  # render imports OpenCV: loaded where frames are rendered
    from freipose.synth.render import CameraRenderer

PAPER = 0.86  # reflectance of the white paper
INK = 0.06  # reflectance of the black print
BACK = 0.45  # reflectance of the board's back


def default_board(arena: ArenaConfig | None = None) -> Any:
    """A ChArUco board sized for the arena (5 x 4 squares of ~70 mm, DICT_4X4_50)."""
    from freipose.calibration.boards import CharucoBoard

    arena = arena or ArenaConfig()
    sq = float(round(min(arena.size) * 0.115))
    return CharucoBoard(
        squares_x=5,
        squares_y=4,
        square_size=sq,
        marker_size=round(0.75 * sq),
        dictionary="DICT_4X4_50",
    )


def _rotation(normal: np.ndarray, roll: float) -> np.ndarray:
    """Board rotation (columns x, y, z in world) whose printed side faces ``normal``.

    Without roll, the board's x axis is horizontal (continuous in the normal's azimuth, so a
    smoothly moving normal gives a smoothly moving board).
    """
    z = -normal / np.linalg.norm(normal)
    az = math.atan2(normal[1], normal[0])
    x = np.array([-math.sin(az), math.cos(az), 0.0])
    y = np.cross(z, x)
    c, s = math.cos(roll), math.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    return np.stack([x, y, z], axis=1)


def board_poses(
    n_frames: int,
    arena_size_mm: tuple[float, float] = (600.0, 600.0),
    rng: np.random.Generator | int | None = 0,
    board_size_mm: tuple[float, float] = (350.0, 280.0),
    floor_frames: int | None = None,
    height_range: tuple[float, float] = (140.0, 320.0),
) -> np.ndarray:
    """Board->world transforms (F, 4, 4) of a board waved through the arena.

    The first ``floor_frames`` (default: 5 % of the frames, at least 1) show the board lying
    flat on the floor, printed side up, centred, its x axis along world x (for
    ``--origin-frame``); then it rises and moves smoothly, tilting, its printed side turning
    round to face every camera in turn (at least 1.5 turns; one per 150 frames in long
    videos) at 30-75 degrees elevation.
    """
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    if n_frames < 1:
        raise SynthError(f"n_frames must be >= 1, got {n_frames}")
    bw, bh = (float(v) for v in board_size_mm)
    half = np.asarray(arena_size_mm, dtype=np.float64) / 2
    nf = max(1, n_frames // 20) if floor_frames is None else int(floor_frames)
    nf = min(nf, n_frames)
    poses = np.tile(np.eye(4), (n_frames, 1, 1))
    R_floor = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])
    t_floor = np.array([0.0, 0, 0.5]) - R_floor @ np.array([bw / 2, bh / 2, 0])
    poses[:nf, :3, :3] = R_floor
    poses[:nf, :3, 3] = t_floor
    n_move = n_frames - nf
    if n_move <= 0:
        return poses
    n_lift = min(n_move // 3, 25)  # first pick the board up from the floor smoothly
    n_wave = n_move - n_lift
    n_keys = max(4, n_wave // 25 + 2)
    keys_t = np.linspace(0.0, 1.0, n_keys)
    cx = rng.uniform(-0.3, 0.3, n_keys) * half[0]
    cy = rng.uniform(-0.3, 0.3, n_keys) * half[1]
    cz = rng.uniform(*height_range, n_keys)
    elev = np.deg2rad(rng.uniform(30, 75, n_keys))
    az0 = rng.uniform(0, 2 * np.pi)
    turns = max(1.5, n_wave / 150.0)  # every camera sees the front; >= 2.4 deg per frame
    az = az0 + 2 * np.pi * turns * keys_t + rng.normal(0, 0.3, n_keys)
    roll = rng.uniform(-0.6, 0.6, n_keys)
    tt = np.concatenate([np.zeros(n_lift), (np.arange(n_wave) + 0.5) / n_wave])
    from scipy.interpolate import CubicSpline

    def smooth(v: np.ndarray) -> np.ndarray:
        return CubicSpline(keys_t, v, bc_type="clamped")(tt)

    pc = np.stack([smooth(cx), smooth(cy), smooth(cz)], -1)
    el, a, rl = smooth(elev), smooth(az), smooth(roll)
    corners = np.array([[0, 0, 0], [bw, 0, 0], [bw, bh, 0], [0, bh, 0.0]])
    centre = np.array([bw / 2, bh / 2, 0.0])
    from scipy.spatial.transform import Rotation, Slerp

    for i in range(n_move):
        nrm = np.array([math.cos(el[i]) * math.cos(a[i]), math.cos(el[i]) * math.sin(a[i]),
                        math.sin(el[i])])  # fmt: skip
        R = _rotation(nrm, rl[i])
        c = pc[i]
        if i < n_lift:
            w = float(_smooth01((i + 1) / (n_lift + 1)))
            slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([R_floor, R])))
            R = slerp([w]).as_matrix()[0]
            c = (1 - w) * np.array([0.0, 0.0, 0.5]) + w * c
        t = c - R @ centre
        low = (corners @ R.T + t)[:, 2].min()
        if low < 0.5:
            t[2] += 0.5 - low
        poses[nf + i, :3, :3] = R
        poses[nf + i, :3, 3] = t
    return poses


def _smooth01(x: float) -> float:
    x = min(max(x, 0.0), 1.0)
    return x * x * (3 - 2 * x)


def _board_box(cam: Camera, corners_world: np.ndarray) -> tuple[int, int, int, int]:
    """Image box x0, y0, x1, y1 (exclusive) of the board with world corners (4, 3).

    The whole image when a corner is behind the camera.
    """
    w, h = cam.size
    depth = corners_world @ cam.R[2] + cam.t[2]
    if np.any(depth <= 1.0):
        return 0, 0, w, h
    edges = np.concatenate(
        [
            corners_world + s * (np.roll(corners_world, -1, 0) - corners_world)
            for s in np.linspace(0, 1, 9)
        ]
    )
    uv = project(edges, cam)
    lo = np.floor(uv.min(0) - 4)
    hi = np.ceil(uv.max(0) + 5)
    x0, y0 = int(np.clip(lo[0], 0, w)), int(np.clip(lo[1], 0, h))
    x1, y1 = int(np.clip(hi[0], 0, w)), int(np.clip(hi[1], 0, h))
    return x0, y0, x1, y1


class _BoardTexture:
    """The board's reflectance texture (computed once; shared by all cameras)."""

    def __init__(
        self, board: Any, px_per_mm: float, margin_mm: float | None, transparent: bool = False
    ) -> None:
        self.transparent = bool(transparent)  # the back shows the pattern (mirrored)
        tex = np.asarray(board.texture(px_per_mm), dtype=np.float32) / 255.0
        self.refl = (INK + (PAPER - INK) * tex).astype(np.float32)
        self.size_mm = tuple(float(v) for v in board.size_mm)
        self.ppm = float(px_per_mm)
        sq = float(min(self.size_mm)) / 4
        self.margin = float(0.5 * sq if margin_mm is None else margin_mm)


def _render_board_on(
    renderer: CameraRenderer,
    tex: _BoardTexture,
    pose: np.ndarray,
    samples: int = 3,
    blur_sigma: float = 0.45,
) -> tuple[tuple[int, int, int, int], np.ndarray] | None:
    """Linear BGR of the board region composited over the background, or None if not seen."""
    import cv2

    from freipose.synth.render import LIGHT

    cam = renderer.camera
    R, t = pose[:3, :3], pose[:3, 3]
    bw, bh = tex.size_mm
    m = tex.margin
    corners = (
        np.array([[-m, -m, 0], [bw + m, -m, 0], [bw + m, bh + m, 0], [-m, bh + m, 0.0]]) @ R.T + t
    )
    x0, y0, x1, y1 = _board_box(cam, corners)
    if x1 <= x0 or y1 <= y0:
        return None
    ray_du, ray_dv = renderer.ray_derivatives()
    Rt = R.T.astype(np.float32)

    def to_board(field: np.ndarray) -> list[np.ndarray]:
        f = field[:, y0:y1, x0:x1]
        return [Rt[i, 0] * f[0] + Rt[i, 1] * f[1] + Rt[i, 2] * f[2] for i in range(3)]

    d0, du, dv = (to_board(f) for f in (renderer.rays_soa, ray_du, ray_dv))
    o_b = R.T @ (renderer.origin - t)
    front = o_b[2] < 0  # the camera sees the printed side
    nrm = R[:, 2] * (1.0 if not front else -1.0)  # normal facing the camera
    lam = 0.45 + 0.55 * abs(float(nrm @ LIGHT))
    depth_bg = renderer.bg_depth[y0:y1, x0:x1]
    if renderer.origin[2] < 0:  # a camera below the floor sees through it
        depth_bg = np.full_like(depth_bg, np.inf)
    offs = (np.arange(samples) + 0.5) / samples - 0.5
    cover = np.zeros((y1 - y0, x1 - x0), np.float32)
    value = np.zeros((y1 - y0, x1 - x0), np.float32)
    ox_, oy_, oz_ = (np.float32(v) for v in o_b)
    for oy in offs:
        for ox in offs:
            fx, fy = np.float32(ox), np.float32(oy)
            dz = d0[2] + fx * du[2] + fy * dv[2]
            with np.errstate(divide="ignore", invalid="ignore"):
                s = -oz_ / dz
            bx = ox_ + s * (d0[0] + fx * du[0] + fy * dv[0])
            by = oy_ + s * (d0[1] + fx * du[1] + fy * dv[1])
            on = (s > 0) & (s < depth_bg) & (bx >= -m) & (bx <= bw + m)
            on &= (by >= -m) & (by <= bh + m)
            val: np.ndarray | np.float32
            if front or tex.transparent:
                mx = bx * np.float32(tex.ppm) - np.float32(0.5)
                my = by * np.float32(tex.ppm) - np.float32(0.5)
                val = cv2.remap(
                    tex.refl, mx, my, cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=PAPER,
                )  # fmt: skip
            else:
                val = np.float32(BACK)
            cover += on
            value += np.where(on, val, np.float32(0))
    n = samples * samples
    cover /= n
    value /= n
    if not cover.any():
        return None
    shade = renderer.shade[y0:y1, x0:x1] * lam
    out = value[..., None] * shade + (1 - cover)[..., None] * renderer.bg_lin[y0:y1, x0:x1]
    if blur_sigma > 0:
        out = cv2.GaussianBlur(out, (0, 0), blur_sigma)
    return (x0, y0, x1, y1), out


def render_board_frames(
    rig: CameraRig,
    board: Any,
    poses: np.ndarray,
    seed: int = 0,
    noise: bool = True,
    blur: bool = True,
    arena: ArenaConfig | None = None,
    px_per_mm: float | None = None,
    margin_mm: float | None = None,
    transparent: bool = False,
) -> dict[str, list[np.ndarray]]:
    """Render the board at ``poses`` (F, 4, 4) in every camera: camera name -> F BGR uint8 images.

    Exact inverse-mapping rendering with lens distortion, 3 x 3 anti-aliasing, the arena as
    background (walls occlude the board), per-camera exposure, optional mild optics blur and
    sensor noise. Deterministic in ``seed``. ``transparent``: cameras behind the board see its
    pattern mirrored (a transparent or double-sided print) instead of a grey back.
    """
    tex = _BoardTexture(board, px_per_mm or _auto_ppm(rig), margin_mm, transparent)
    return {
        cam.name: list(_iter_board_camera(cam, ci, tex, poses, seed, noise, blur, arena))
        for ci, cam in enumerate(rig)
    }


def _iter_board_camera(
    cam: Camera,
    ci: int,
    tex: _BoardTexture,
    poses: np.ndarray,
    seed: int,
    noise: bool,
    blur: bool,
    arena: ArenaConfig | None,
    style: SceneStyle | None = None,
) -> Iterator[np.ndarray]:
    """The board frames (H, W, 3) BGR uint8 of camera number ``ci`` at ``poses`` (F, 4, 4).

    ``style``: the scene's photometric settings (grayscale sensor, floor, lighting, blur,
    noise level; None: the classic scene's).
    """
    from freipose.synth.render import CameraLook, CameraRenderer

    arena = arena or ArenaConfig()
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise SynthError(f"poses must have shape (F, 4, 4), got {poses.shape}")
    cam_seed = int(np.random.SeedSequence([int(seed), 7, ci]).generate_state(1)[0])
    look = CameraLook.random(np.random.default_rng(cam_seed))
    if not noise:
        look = replace(look, noise_sigma=0.0)
    r = CameraRenderer(cam, arena, cam_seed, look, style)
    rng = np.random.default_rng(cam_seed + 1)
    for pose in poses:
        res = _render_board_on(r, tex, pose, blur_sigma=0.45 if blur else 0.0)
        if res is None:
            yield r.finish(None, None, rng)
        else:
            box, lin = res
            yield r.finish(lin, box, rng)


def _auto_ppm(rig: CameraRig) -> float:
    """Texture resolution: about 3 texels per image pixel for a board 60 cm from a camera."""
    f = float(max(max(c.K[0, 0], c.K[1, 1]) for c in rig))
    return float(np.clip(3.0 * f / 600.0, 1.0, 8.0))


@dataclass(frozen=True, eq=False)
class _BoardJob:
    """What a worker needs to render one camera's board video.

    Attributes:
        camera: the camera.
        index: the camera's number in the rig (selects its look and noise).
        texture: the board's texture.
        poses: (F, 4, 4) board->world transforms.
        seed: the recording's seed.
        fps: frame rate.
        path: the video file to write.
        arena: the arena (background).
    """

    camera: Camera
    index: int
    texture: _BoardTexture
    poses: np.ndarray
    seed: int
    fps: float
    path: Path
    arena: ArenaConfig
    style: SceneStyle | None = None


def _board_camera_job(job: _BoardJob) -> str:
    """Worker: render and write one camera's board video (module level so it can be pickled)."""
    import cv2

    from freipose.io.video import VideoWriter

    cv2.setNumThreads(1)
    cam = job.camera
    frames = _iter_board_camera(
        cam, job.index, job.texture, job.poses, job.seed, True, True, job.arena, job.style
    )
    with VideoWriter(job.path, job.fps, cam.size) as w:
        for img in frames:
            w.write(img)
    return str(job.path)


def write_board_videos(
    outdir: str | Path,
    rig: CameraRig,
    board: Any,
    n_frames: int,
    seed: int = 0,
    fps: float = 25.0,
    fmt: str = ".mkv",
    arena: ArenaConfig | None = None,
    workers: int = 1,
    progress: bool | None = None,
    transparent: bool = False,
    styles: Mapping[str, SceneStyle] | None = None,
) -> tuple[dict[str, Path], np.ndarray]:
    """Write a calibration recording: one board video per camera plus the ground truth.

    Writes ``outdir/<camera><fmt>``, ``true_calibration.toml`` (the true rig), ``board.toml``
    (the board) and ``board_poses.npy`` ((F, 4, 4) board->world transforms). Running it
    again with the same arguments keeps the videos already written (resume). ``transparent``:
    cameras behind the board see its pattern mirrored (see :func:`render_board_frames`).
    ``styles``: per camera name, the scene's photometric settings (default: the classic
    scene's). The board's heights scale with the arena (140-320 mm for a 600 mm arena) and
    rise with walls taller than a sixth of the arena.

    Returns:
        ``(videos {camera: path}, poses (F, 4, 4))``.
    """
    import hashlib
    import json

    from freipose.calibration.board_files import save_board
    from freipose.io.atomic import atomic_path, atomic_write_text
    from freipose.io.calibration import save_calibration
    from freipose.io.calibration_toml import rig_to_toml_text
    from freipose.io.session import TRUE_CALIBRATION_NAME

    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    arena = arena or _arena_from(rig)
    # heights scale with the arena (and the rig), and stay over walls taller than 1/6 of it
    reach = float(max(arena.size)) / 600.0
    lift = max(0.0, arena.wall_height - 100.0 * reach)
    heights = (140.0, 320.0)
    if reach != 1.0 or lift > 0:
        heights = (140.0 * reach + lift, 320.0 * reach + lift)
    poses = board_poses(
        n_frames, arena.size, np.random.default_rng(seed), board.size_mm, height_range=heights
    )
    # what the videos depend on; complete videos of the same recording are kept (resume)
    stamp = hashlib.sha256(json.dumps([
        rig_to_toml_text(rig), repr(board), n_frames, int(seed), float(fps), fmt,
        list(arena.size), arena.wall_height, *(["transparent"] if transparent else []),
        *([repr(sorted(styles.items()))] if styles else []),
        *([list(heights)] if heights != (140.0, 320.0) else []),
    ]).encode()).hexdigest()  # fmt: skip
    stamp_path = out / ".synth_board_stamp"
    same = stamp_path.is_file() and stamp_path.read_text(encoding="utf-8") == stamp
    stamp_path.unlink(missing_ok=True)
    save_calibration(rig, out / TRUE_CALIBRATION_NAME)
    save_board(board, out / "board.toml")
    with atomic_path(out / "board_poses.npy") as tmp, open(tmp, "wb") as fh:
        np.save(fh, poses)
    videos = {cam.name: out / f"{cam.name}{fmt}" for cam in rig}
    tex = _BoardTexture(board, _auto_ppm(rig), None, transparent)
    jobs = [
        _BoardJob(
            cam, ci, tex, poses, seed, fps, videos[cam.name], arena, (styles or {}).get(cam.name)
        )  # fmt: skip
        for ci, cam in enumerate(rig)
        if not (same and videos[cam.name].is_file())
    ]
    atomic_write_text(stamp_path, stamp)
    run_jobs(_board_camera_job, jobs, max(1, min(workers, len(jobs))), "render board", progress)
    return videos, poses


def _arena_from(rig: CameraRig) -> ArenaConfig:
    """The arena recorded in the rig's metadata (default arena when none is)."""
    md = rig.metadata
    if "arena_size" in md:
        return ArenaConfig(tuple(md["arena_size"]), float(md.get("arena_wall_height", 100.0)))
    return ArenaConfig()
