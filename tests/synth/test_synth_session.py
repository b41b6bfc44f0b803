"""Whole sessions: labels match the written calibration, occlusion flags, reproducibility."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from freipose.geometry import Camera, CameraRig, project
from freipose.io.calibration import load_calibration
from freipose.io.labels import read_labels_h5
from freipose.io.video import FrameSource, find_camera_videos
from freipose.synth import (
    RAT_KEYPOINTS,
    ArenaConfig,
    RatBody,
    SceneConfig,
    StimulationConfig,
    build_body,
    generate_session,
    keypoint_visibility,
    simulate_motion,
)
from freipose.synth.body import KEYPOINT_OWNERS
from freipose.synth.render import CameraRenderer

TINY = dict(n_cameras=3, frames=4, size=(160, 128), video_format=".mkv")


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "s1"
    cfg = SceneConfig(
        **TINY, seed=11, stimulation=StimulationConfig(onset_s=0.02, duration_s=0.04, spacing_s=0.0)
    )
    return cfg, generate_session(out, cfg, workers=1, progress=False)


def test_session_layout(session):
    cfg, paths = session
    assert set(find_camera_videos(paths.folder)) == {"cam0", "cam1", "cam2"}
    for p in paths.videos.values():
        src = FrameSource(p)
        assert src.num_frames == 4 and src.size == (160, 128)
    rows = list(csv.reader(paths.events.open()))
    assert rows[0] == ["start_s", "end_s"] and [float(v) for v in rows[1]] == [0.02, 0.06]
    assert SceneConfig.from_toml(paths.scene) == cfg


def test_labels_are_projections_through_written_calibration(session):
    cfg, paths = session
    rig = load_calibration(paths.calibration)
    labels = read_labels_h5(paths.labels)
    assert labels.keypoints == RAT_KEYPOINTS and labels.cameras == tuple(rig.names)
    assert len(labels) == cfg.frames and np.all(np.isfinite(labels.points3d))
    info = labels.sessions["s1"]
    assert info.fps == cfg.fps and info.videos["cam0"] == "cam0.mkv"
    assert info.calibration.allclose(rig, atol=1e-9)
    proj = rig.project(labels.points3d)  # (N, C, K, 2)
    assert np.abs(proj - labels.points2d).max() < 0.01
    assert labels.visible2d.shape == (4, 3, 12) and labels.visible2d.any()


def test_same_seed_same_bytes(session, tmp_path):
    cfg, paths = session
    again = generate_session(tmp_path / "s1", cfg, workers=1, progress=False)
    for cam in paths.videos:
        a, b = FrameSource(paths.videos[cam]), FrameSource(again.videos[cam])
        for i in range(cfg.frames):
            np.testing.assert_array_equal(a.read(i), b.read(i))
    la, lb = read_labels_h5(paths.labels), read_labels_h5(again.labels)
    np.testing.assert_array_equal(la.points2d, lb.points2d)
    np.testing.assert_array_equal(la.points3d, lb.points3d)
    np.testing.assert_array_equal(la.visible2d, lb.visible2d)
    assert paths.scene.read_text() == again.scene.read_text()
    other = generate_session(
        tmp_path / "s2", SceneConfig(**TINY, seed=12), workers=1, progress=False
    )
    assert not np.array_equal(
        FrameSource(other.videos["cam0"]).read(0), FrameSource(paths.videos["cam0"]).read(0)
    )


def test_resume_and_refuse_other_scene(session, tmp_path):
    cfg, _ = session
    out = tmp_path / "s"
    paths = generate_session(out, cfg, workers=1, progress=False)
    paths.videos["cam1"].unlink()  # as if interrupted
    before = paths.videos["cam0"].stat().st_mtime_ns
    generate_session(out, cfg, workers=1, progress=False)
    assert paths.videos["cam1"].is_file() and paths.videos["cam0"].stat().st_mtime_ns == before
    with pytest.raises(ValueError, match="different scene"):
        generate_session(out, SceneConfig(**TINY, seed=99), workers=1, progress=False)
    generate_session(out, SceneConfig(**TINY, seed=99), workers=1, progress=False, overwrite=True)


def _side_rig() -> CameraRig:
    """Low cameras looking at the animal from its left (+y), right (-y), back and front."""
    kw = dict(size=(320, 256), focal=400.0)
    return CameraRig((
        Camera.look_at("left", (20, 450, 30), (20, 0, 20), **kw),
        Camera.look_at("right", (20, -450, 30), (20, 0, 20), **kw),
        Camera.look_at("behind", (-500, 0, 60), (0, 0, 20), **kw),
        Camera.look_at("front", (500, 0, 60), (0, 0, 20), **kw),
    ))  # fmt: skip


def test_paw_behind_the_body_is_occluded():
    body = RatBody(appearance="albino")
    state = simulate_motion(1, 50.0, np.random.default_rng(0), body, start=(0.0, 0.0, 0.0))
    geom = build_body(body, state)  # standing at the origin, facing +x
    rig = _side_rig()
    open_field = ArenaConfig(wall_height=0.0)  # no walls between the low cameras and the rat
    pts, vis = keypoint_visibility(geom, rig, open_field)
    k = {n: i for i, n in enumerate(RAT_KEYPOINTS)}
    left, right = 0, 1
    for name in ("Paw Front Right", "Paw Back Right Ankle", "Eye Right", "Ear Right"):
        assert not vis[0, left, k[name]], name  # right side seen from the left: hidden
        assert vis[0, right, k[name]], name
    for name in ("Paw Front Left", "Eye Left", "Ear Left"):
        assert vis[0, left, k[name]] and not vis[0, right, k[name]], name
    assert vis[0, 2, k["Tail"]] and not vis[0, 3, k["Tail"]]  # tail root: seen from behind only
    assert vis[0, 3, k["Nose"]] and not vis[0, 2, k["Nose"]]
    # the rendered z-buffer agrees: the pixel of the hidden right paw shows another part
    r = CameraRenderer(rig["left"], open_field, seed=0)
    (x0, y0, x1, y1), _, pid = r.render_animal(geom, 0, body.palette)
    for name in ("Paw Front Right", "Eye Right"):
        u, v = np.round(pts[0, left, k[name]]).astype(int)
        shown = pid[v - y0, u - x0]
        assert shown >= 0 and shown not in KEYPOINT_OWNERS[k[name]], name
    for name in ("Paw Front Left", "Eye Left", "Nose"):
        u, v = np.round(pts[0, left, k[name]]).astype(int)
        assert pid[v - y0, u - x0] >= 0, name  # a visible keypoint lies on the animal


def test_outside_the_image_is_not_visible():
    body = RatBody()
    state = simulate_motion(1, 50.0, np.random.default_rng(0), body, start=(0.0, 0.0, 0.0))
    geom = build_body(body, state)
    cam = Camera.look_at("c", (0, 0, 900), (200, 0, 0), (64, 64), 300.0, up=(0, 1, 0))
    pts, vis = keypoint_visibility(geom, CameraRig((cam,)), None)
    outside = (pts[0, 0] < -0.5).any(-1) | (pts[0, 0] > 63.5).any(-1)
    assert outside.any() and not vis[0, 0][outside].any()
    np.testing.assert_allclose(pts[0, 0], project(geom.keypoints[0], cam))


def test_rendered_animal_is_where_the_labels_are(session):
    cfg, paths = session
    labels = read_labels_h5(paths.labels)
    for ci, cam in enumerate(labels.cameras):
        frame = FrameSource(paths.videos[cam]).read(2).astype(float)
        pts = labels.points2d[2, ci]
        c = np.nanmean(pts, 0)
        # the animal differs from the floor: strong local contrast near the labels
        x, y = int(np.clip(c[0], 8, 151)), int(np.clip(c[1], 8, 119))
        patch = frame[y - 8 : y + 8, x - 8 : x + 8]
        assert patch.std() > 8.0


def test_animal_out_of_view_renders_the_arena():
    body = RatBody()
    geom = build_body(
        body, simulate_motion(1, 50.0, np.random.default_rng(0), body, start=(0, 0, 0))
    )
    cam = Camera.look_at("c", (0, 0, 900), (280, 280, 0), (64, 48), 200.0, up=(0, 1, 0))
    r = CameraRenderer(cam, ArenaConfig(), seed=0)
    img = r.render(geom, 0, body.palette, np.random.default_rng(0))
    assert img.shape == (48, 64, 3) and img.dtype == np.uint8
    _, vis = keypoint_visibility(geom, CameraRig((cam,)), ArenaConfig())
    assert not vis.any()


def test_appearances_and_config_validation():
    hooded, albino = RatBody(appearance="hooded").palette, RatBody(appearance="albino").palette
    head, eye = 2, 5  # material indices of MATERIALS
    assert hooded[head].max() < 0.2 and albino[head].min() > 0.7  # black hood vs white head
    assert albino[eye, 0, 2] > 0.5 > albino[eye, 0, 0]  # red (BGR) albino eyes
    rng = np.random.default_rng(0)
    sizes = [RatBody.random(rng).scale for _ in range(50)]
    assert 0.85 < min(sizes) < 0.95 and 1.05 < max(sizes) < 1.15
    with pytest.raises(ValueError, match="appearance"):
        RatBody(appearance="agouti")
    for bad in (dict(size=(8, 8)), dict(frames=0), dict(fps=0), dict(video_format=".gif"),
                dict(appearance="blue"), dict(n_cameras=0)):  # fmt: skip
        with pytest.raises(ValueError):
            SceneConfig(**bad)
    with pytest.raises(ValueError, match="unknown scene settings"):
        SceneConfig.from_dict({"frame": 3})


def test_animal_seed_films_the_same_animal_on_another_day():
    from freipose.synth.scene import build_scene

    day1 = build_scene(SceneConfig(seed=1, frames=20, appearance="random"))
    day2 = build_scene(SceneConfig(seed=2, frames=20, appearance="random", animal_seed=1))
    other = build_scene(SceneConfig(seed=2, frames=20, appearance="random"))
    assert day2.body == day1.body  # same size, proportions and coat
    assert other.body != day1.body
    assert not np.allclose(day2.geometry.keypoints, day1.geometry.keypoints)  # its own motion
    back = SceneConfig.from_dict(SceneConfig(seed=2, animal_seed=1).to_dict())
    assert back.animal_seed == 1 and "animal_seed" not in SceneConfig(seed=2).to_dict()
    with pytest.raises(ValueError, match="animal_seed"):
        SceneConfig(animal_seed=-1)
