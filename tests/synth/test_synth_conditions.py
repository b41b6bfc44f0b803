"""Conditions of real rigs: grayscale, fisheye, reflections, resting, bedding, mouse, lighting."""

from __future__ import annotations

import numpy as np
import pytest

from freipose.calibration.plausibility import FOV_RANGE_DEG, folding_radius
from freipose.geometry import project
from freipose.io.labels import read_labels_h5
from freipose.io.video import FrameSource
from freipose.synth import (
    ArenaConfig,
    RatBody,
    SceneConfig,
    build_body,
    default_rig,
    generate_session,
    simulate_motion,
)
from freipose.synth.conditions import CONDITION_DEFAULTS
from freipose.synth.look import SceneStyle
from freipose.synth.render import BG_FLOOR, BG_WALL, CameraRenderer
from freipose.synth.scene import build_scene

TINY = dict(n_cameras=3, frames=2, size=(128, 96), video_format=".mkv", seed=4)


def _animal(seed: int = 0, scale: float = 1.0):
    body = RatBody(scale=scale)
    state = simulate_motion(1, 50.0, np.random.default_rng(seed), body, start=(0.0, 0.0, 0.3))
    return body, build_body(body, state)


def test_defaults_are_the_classic_scene():
    cfg = SceneConfig()
    assert not set(cfg.to_dict()) & set(CONDITION_DEFAULTS)  # scene.toml unchanged
    assert cfg.resolved() is cfg
    assert SceneStyle() == SceneStyle(grayscale=False, floor="mat", reflections=0.0)
    rich = SceneConfig(animal="mouse", arena_size=(250, 250), floor="bedding", reflections=0.3)
    d = rich.to_dict()
    assert d["animal"] == "mouse" and d["floor"] == "bedding" and d["reflections"] == 0.3
    assert SceneConfig.from_dict(d) == rich


def test_grayscale_cameras_all_or_by_name(tmp_path):
    paths = generate_session(
        tmp_path / "g", SceneConfig(**TINY, grayscale=("cam1",)), workers=1, progress=False
    )
    for cam, video in paths.videos.items():
        img = FrameSource(video).read(1).astype(int)
        same = np.all(img[..., 0] == img[..., 1]) and np.all(img[..., 1] == img[..., 2])
        assert same == (cam == "cam1"), cam
    assert SceneConfig.from_toml(paths.scene).grayscale == ("cam1",)
    with pytest.raises(ValueError, match="grayscale"):
        SceneConfig(grayscale="cam1")
    rig = tmp_path / "rig.toml"  # or per camera in a rig file
    rig.write_text(
        "[defaults]\nsize = [96, 80]\n"
        '[[camera]]\nname = "mono"\nposition = [700, 0, 650]\nlook_at = [0, 0, 30]\n'
        "grayscale = true\n"
        '[[camera]]\nname = "rgb"\nposition = [0, 700, 650]\nlook_at = [0, 0, 30]\n'
    )
    cfg = SceneConfig(frames=2, video_format=".mkv", rig_file=str(rig))
    paths = generate_session(tmp_path / "r", cfg, workers=1, progress=False)
    mono, rgb = (FrameSource(paths.videos[c]).read(1).astype(int) for c in ("mono", "rgb"))
    assert np.all(mono[..., 0] == mono[..., 2]) and not np.all(rgb[..., 0] == rgb[..., 2])


@pytest.mark.parametrize("layout", ["ring", "above", "side", "below"])
def test_fisheye_rigs_are_plausible_and_see_the_arena(layout):
    for arena in (ArenaConfig(), ArenaConfig((250.0, 250.0), 150.0)):
        for seed in (None, 3, 8):
            rig = default_rig(6, (320, 256), seed=seed, arena=arena, lens="fisheye", layout=layout)
            for cam in rig:
                if cam.center[2] < 0:  # the camera under the floor keeps the standard lens
                    continue
                w, h = cam.size
                K = cam.K
                corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], float)
                rc = np.hypot(*((corners - K[:2, 2]) / K[[0, 1], [0, 1]]).T)
                assert folding_radius(cam.dist, float(rc.max())) is None, (layout, cam.name)
                fov = 2 * np.degrees(np.arctan2(w / 2, K[0, 0]))
                assert FOV_RANGE_DEG[0] <= fov <= FOV_RANGE_DEG[1]
                # strong: the image corner's ray is far out of where a pinhole would see it
                r_u = np.linspace(0, 3 * rc.max(), 3001)
                k1, k2 = cam.dist[0], cam.dist[1]
                r_d = r_u * (1 + k1 * r_u**2 + k2 * r_u**4)
                corner_u = r_u[np.searchsorted(r_d, rc.max())]
                assert corner_u > 1.3 * rc.max()
                uv = project(arena.corners(0.0), cam)
                assert np.all((uv >= -0.5) & (uv <= np.array(cam.size) - 0.5)), (layout, cam.name)


def test_reflections_show_the_animal_in_the_walls_only():
    body, geom = _animal()
    cam = default_rig(1, (160, 128), seed=1)[0]
    arena = ArenaConfig(wall_height=200.0)
    plain = CameraRenderer(cam, arena, seed=3)
    mirror = CameraRenderer(cam, arena, seed=3, style=SceneStyle(reflections=0.5))
    rng = np.random.default_rng
    a = plain.render(geom, 0, body.palette, rng(0)).astype(int)
    b = mirror.render(geom, 0, body.palette, rng(0)).astype(int)
    diff = np.abs(a - b).max(-1) > 0
    assert diff.sum() > 20  # the mirror images are there
    assert np.all(plain.bg_kind[diff] == BG_WALL)  # ... on the walls only


def test_resting_animal_stays_still_for_seconds():
    fps, n = 25.0, 750  # 30 s
    body = RatBody()
    rest = simulate_motion(n, fps, np.random.default_rng(2), body, rest_fraction=0.7)
    active = simulate_motion(n, fps, np.random.default_rng(2), body)

    def still_share(state) -> float:
        kp = build_body(body, state).keypoints
        step = np.linalg.norm(np.diff(kp, axis=0), axis=-1).max(-1)  # fastest keypoint, mm/frame
        still = step < 0.3
        # frames in still runs of at least 2 s
        runs, count = np.zeros(len(still), bool), 0
        for i, s in enumerate(still):
            count = count + 1 if s else 0
            if count >= 2 * fps:
                runs[i - count + 1 : i + 1] = True
        return float(runs.mean())

    assert still_share(rest) > 0.4 and still_share(active) < 0.1


def test_bedding_floor_is_textured():
    arena = ArenaConfig((250.0, 250.0), 60.0)  # a mouse box filmed at about 1 px/mm
    cam = default_rig(1, (320, 256), seed=1, arena=arena)[0]
    mat = CameraRenderer(cam, arena, seed=5)
    bed = CameraRenderer(cam, arena, seed=5, style=SceneStyle(floor="bedding"))
    xy = mat.floor_xy
    inside = (mat.bg_kind == BG_FLOOR) & (np.abs(xy[..., 0]) < 120) & (np.abs(xy[..., 1]) < 120)

    def contrast(r: CameraRenderer) -> float:  # relative spread of the floor's brightness
        g = r.bg_lin.mean(-1)[inside]
        return float(g.std() / g.mean())

    assert contrast(bed) > 1.6 * contrast(mat)
    assert bed.bg_lin[inside][:, 2].mean() > bed.bg_lin[inside][:, 0].mean()  # beige: R > B


def test_mouse_is_small_and_fits_its_arena(tmp_path):
    cfg = SceneConfig(**{**TINY, "frames": 20}, animal="mouse", arena_size=(250.0, 250.0))
    paths = generate_session(tmp_path / "m", cfg, workers=1, progress=False)
    kp = read_labels_h5(paths.labels).points3d
    nose, tail = kp[:, 10], kp[:, 11]
    length = np.linalg.norm(nose - tail, axis=-1)
    assert 70 < np.median(length) < 120  # a rat's is about 2.3 times that
    assert np.all(np.abs(kp[..., :2]) < 125)
    rat = build_body(RatBody(), simulate_motion(1, 50.0, np.random.default_rng(0), RatBody()))
    assert np.linalg.norm(rat.keypoints[0, 10] - rat.keypoints[0, 11]) > 2 * np.median(length)
    with pytest.raises(ValueError, match="animal"):
        SceneConfig(animal="hamster")


def test_lighting_blur_and_noise_settings():
    body, geom = _animal()
    cam = default_rig(1, (160, 128), seed=1)[0]
    arena = ArenaConfig()

    def frame(**style) -> np.ndarray:
        r = CameraRenderer(cam, arena, seed=2, style=SceneStyle(**style))
        return r.render(geom, 0, body.palette, np.random.default_rng(0)).astype(float)

    base = frame()
    assert frame(brightness=1.4).mean() > base.mean() + 10
    assert frame(contrast=1.5).std() > base.std() * 1.2
    grad = frame(light_gradient=0.6) / np.maximum(base, 1)
    assert np.ptp(np.median(grad, axis=(0, 2))) > 0.3 or np.ptp(np.median(grad, axis=(1, 2))) > 0.3

    def sharpness(img: np.ndarray) -> float:
        return float(np.abs(np.diff(img, axis=1)).mean())

    assert sharpness(frame(blur=2.0, noise_level=0.0)) < 0.7 * sharpness(frame(noise_level=0.0))
    assert sharpness(frame(noise_level=3.0)) > 1.5 * sharpness(frame(noise_level=0.0))
    for bad in (dict(brightness=0), dict(blur=-1), dict(reflections=1.5), dict(floor="sand"),
                dict(lens="tele"), dict(layout="circle"), dict(rest_fraction=1.0)):  # fmt: skip
        with pytest.raises(ValueError):
            SceneConfig(**bad)


def test_calibration_video_of_a_mouse_box_keeps_the_board_over_its_walls(tmp_path):
    cfg = SceneConfig(**{**TINY, "frames": 1}, animal="mouse", arena_size=(250.0, 250.0),
                      wall_height=120.0, grayscale=True, calibration_video=True,
                      calibration_frames=12)  # fmt: skip
    paths = generate_session(tmp_path / "c", cfg, workers=1, progress=False)
    from freipose.calibration.board_files import load_board

    poses = np.load(paths.folder / "calibration" / "board_poses.npy")
    bw, bh = load_board(paths.board).size_mm
    centres = poses[:, :3, :3] @ np.array([bw / 2, bh / 2, 0.0]) + poses[:, :3, 3]
    assert centres[0, 2] < 5 and np.all(centres[-4:, 2] > 130.0)  # on the floor, then high up
    for video in paths.calibration_videos.values():  # the scene's grayscale cameras
        img = FrameSource(video).read(8)
        assert np.array_equal(img[..., 0], img[..., 1]) and np.array_equal(img[..., 1], img[..., 2])


def test_acrylic_walls_let_the_cameras_see_and_label_the_animal_through_them(tmp_path):
    base = dict(**{**TINY, "frames": 2}, animal="mouse", arena_size=(250.0, 250.0),
                wall_height=150.0)  # fmt: skip
    opaque = generate_session(tmp_path / "o", SceneConfig(**base), workers=1, progress=False)
    cfg = SceneConfig(**base, walls="acrylic", reflections=0.3)
    acrylic = generate_session(tmp_path / "a", cfg, workers=1, progress=False)
    vo, va = (read_labels_h5(p.labels).visible2d for p in (opaque, acrylic))
    assert np.all(va >= vo) and va.sum() > vo.sum()  # the walls hide nothing any more
    scene = build_scene(cfg)
    cam = scene.rig[0]
    r = CameraRenderer(cam, scene.arena, seed=1, style=SceneStyle(walls="acrylic"))
    (x0, y0, _, _), _, pid = r.render_animal(scene.geometry, 1, scene.body.palette)
    labels = read_labels_h5(acrylic.labels)
    behind = va[1, 0] & ~vo[1, 0]  # seen through a wall in camera 0
    assert behind.any()
    for u, v in np.round(labels.points2d[1, 0][behind]).astype(int):  # the animal is there
        assert (pid[v - y0 - 1 : v - y0 + 2, u - x0 - 1 : u - x0 + 2] >= 0).any()
    assert np.all(r.bg_kind != BG_WALL) and (r.wall_id >= 0).any()  # panes, and mirrors
