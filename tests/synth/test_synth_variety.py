"""Label files as other tools write them, domain randomisation, a camera under the floor."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.io.labels import read_labels_h5
from freipose.io.session import CALIBRATION_NAMES
from freipose.synth import (
    RAT_KEYPOINTS,
    RatBody,
    SceneConfig,
    build_body,
    default_rig,
    generate_session,
    keypoint_visibility,
    simulate_motion,
)
from freipose.synth.render import CameraRenderer
from freipose.synth.rig import ArenaConfig

TINY = dict(n_cameras=3, frames=6, size=(128, 96), video_format=".mkv", seed=7)


def test_sleap_and_dlc_label_files_hold_noisy_visible_points(tmp_path):
    sio = pytest.importorskip("sleap_io")
    cfg = SceneConfig(**TINY, label_files=("sleap", "dlc"), label_noise_px=1.5)
    paths = generate_session(tmp_path / "s", cfg, workers=1, progress=False)
    truth = read_labels_h5(paths.labels)
    cams = ("cam0", "cam1", "cam2")
    assert {p.relative_to(paths.folder).as_posix() for p in paths.label_files} == {
        *(f"{c}/{c}.slp" for c in cams),
        *(f"labeled-data/s_{c}/CollectedData_synthetic.csv" for c in cams),
    }
    errors = []
    for ci, cam in enumerate(truth.cameras):
        labels = sio.load_slp(str(paths.folder / cam / f"{cam}.slp"))
        assert [n.name for n in labels.skeletons[0].nodes] == list(RAT_KEYPOINTS)
        assert labels.videos[0].filename == f"../{cam}.mkv"  # next to the session's videos
        for lf in labels.labeled_frames:
            (inst,) = lf.instances
            assert type(inst).__name__ == "PredictedInstance" and 0 < inst.score <= 1
            pts = inst.numpy()
            vis = truth.visible2d[lf.frame_idx, ci]
            np.testing.assert_array_equal(np.isfinite(pts[:, 0]), vis)  # visible points only
            errors.append(pts[vis] - truth.points2d[lf.frame_idx, ci, vis])
            sc = inst.points["score"][vis]
            assert np.all((sc > 0) & (sc <= 1))
        table = paths.folder / "labeled-data" / f"s_{cam}" / "CollectedData_synthetic.csv"
        rows = list(csv.reader(table.open()))
        assert rows[0][0] == "scorer" and rows[1][1:3] == ["Ear Right", "Ear Right"]
        assert rows[2][1:3] == ["x", "y"] and len(rows) == 3 + len(labels.labeled_frames)
    e = np.concatenate(errors)
    assert 1.0 < e.std() < 2.0 and abs(e.mean()) < 0.5  # the requested 1.5 px noise
    with pytest.raises(ValueError, match="label_files"):
        SceneConfig(label_files=("nwb",))


def test_randomize_draws_varied_reproducible_scenes(tmp_path):
    drawn = [SceneConfig(seed=s, frames=5, randomize=True).resolved() for s in range(40)]
    assert drawn[3] == SceneConfig(seed=3, frames=5, randomize=True).resolved()
    assert all(not d.randomize and d.frames == 5 for d in drawn)
    assert {d.appearance for d in drawn} == {"hooded", "albino", "dark"}
    assert {d.layout for d in drawn} == {"ring", "above", "side", "below"}
    assert {d.lens for d in drawn} == {"standard", "fisheye", "pinhole"}
    assert {d.walls for d in drawn} == {"opaque", "acrylic"} and {d.floor for d in drawn} == {
        "mat",
        "bedding",
    }
    assert {d.animal for d in drawn} == {"rat", "mouse"} and {d.grayscale for d in drawn} == {
        True,
        False,
    }
    assert {d.n_cameras for d in drawn} <= set(range(3, 9)) and len({d.size for d in drawn}) > 3
    scales = [d.animal_scale for d in drawn]
    assert min(scales) < 0.5 and max(scales) > 0.95
    cfg = SceneConfig(seed=5, frames=2, size=(96, 80), video_format=".mkv", randomize=True)
    assert cfg.resolved().size == (96, 80)  # given settings are kept
    assert cfg.resolved().layout == SceneConfig(seed=5, randomize=True).resolved().layout
    paths = generate_session(tmp_path / "r", cfg, workers=1, progress=False)
    again = SceneConfig.from_toml(paths.scene)
    assert again == cfg.resolved() and len(paths.videos) == again.n_cameras


def test_camera_below_the_transparent_floor_sees_the_animal_from_below(tmp_path):
    arena = ArenaConfig()
    rig = default_rig(4, (160, 128), seed=2, arena=arena, layout="below")
    below = rig["cam3"]
    assert below.center[2] < 0 and all(c.center[2] > 0 for c in list(rig)[:3])
    body = RatBody(appearance="albino")
    geom = build_body(
        body, simulate_motion(1, 50.0, np.random.default_rng(0), body, start=(0, 0, 0))
    )
    pts, vis = keypoint_visibility(geom, rig, arena)
    k = {n: i for i, n in enumerate(RAT_KEYPOINTS)}
    assert vis[0, 3, k["Paw Front Right"]] and vis[0, 3, k["Paw Back Left Tip"]]
    r = CameraRenderer(below, arena, seed=0)
    (x0, y0, x1, y1), _, pid = r.render_animal(geom, 0, body.palette)
    for name in ("Paw Front Right", "Paw Back Left Tip"):
        u, v = np.round(pts[0, 3, k[name]]).astype(int)
        assert pid[v - y0, u - x0] >= 0, name  # seen through the floor
    assert np.isinf(r.bg_depth[(r.bg_kind == 0)]).all()


def test_synth_command_with_the_conditions_of_a_lab_rig(tmp_path):
    pytest.importorskip("sleap_io")
    out = tmp_path / "mouse"
    args = ["synth", str(out), "--frames", "3", "--size", "128x96", "--cameras", "3",
            "--animal", "mouse", "--arena-size", "250x250", "--wall-height", "120",
            "--grayscale", "--lens", "fisheye", "--reflections", "0.3", "--rest-fraction", "0.5",
            "--floor", "bedding", "--label-files", "sleap", "--lossless"]  # fmt: skip
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 0, res.output
    assert (out / "cam2" / "cam2.slp").is_file() and (out / "true_calibration.toml").is_file()
    assert not (out / "calibration.toml").exists() and "true_calibration.toml" in CALIBRATION_NAMES
    cfg = SceneConfig.from_toml(out / "scene.toml")
    assert (cfg.animal, cfg.arena_size, cfg.lens, cfg.floor) == (
        "mouse",
        (250.0, 250.0),
        "fisheye",
        "bedding",
    )
    assert cfg.grayscale is True and cfg.label_files == ("sleap",) and cfg.rest_fraction == 0.5
    res = CliRunner().invoke(cli, ["synth", str(tmp_path / "x"), "--label-files", "nwb"])
    assert res.exit_code == 1 and "label_files" in res.output


@pytest.mark.parametrize("fmt", ["sleap", "dlc"])
def test_label_files_import_into_freipose_and_triangulate_near_the_truth(tmp_path, fmt):
    if fmt == "sleap":
        pytest.importorskip("sleap_io")
    cfg = SceneConfig(**{**TINY, "frames": 8, "size": (160, 128)}, label_files=(fmt,))
    paths = generate_session(tmp_path / "s1", cfg, workers=1, progress=False)
    source = paths.folder if fmt == "sleap" else paths.folder / "labeled-data"
    out = tmp_path / "labels.h5"
    args = ["labels", "import", "--format", fmt, str(source), "--skeleton", "rat",
            "--calibration", str(paths.calibration), "-o", str(out)]  # fmt: skip
    if fmt == "sleap":
        args += ["--instances", "predicted"]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 0, res.output
    got, truth = read_labels_h5(out), read_labels_h5(paths.labels)
    assert got.cameras == truth.cameras and len(got) == cfg.frames
    err = np.linalg.norm(got.points3d - truth.points3d[got.frame_index], axis=-1)
    assert np.isfinite(err).sum() >= 3 * cfg.frames and np.nanmedian(err) < 8.0


def test_rig_with_a_camera_below_the_floor_films_a_double_sided_board(tmp_path):
    """The camera under the floor sees the board's pattern (mirrored), so the rig calibrates."""
    from freipose.calibration.board_files import load_board
    from freipose.calibration.detect_videos import detect_cameras

    cfg = SceneConfig(n_cameras=3, frames=2, size=(320, 256), seed=3, layout="below",
                      calibration_video=True, calibration_frames=30)  # fmt: skip
    paths = generate_session(tmp_path / "s", cfg, workers=1, progress=False)
    board = load_board(paths.board)
    vids = {p.stem: p for p in sorted((tmp_path / "s" / "calibration").glob("cam*.mp4"))}
    dets = detect_cameras([vids[n] for n in ("cam0", "cam1", "cam2")], board, jobs=1,
                          progress=False)  # fmt: skip
    seen = int((dets[2].counts >= 4).sum())
    assert seen >= 10
    assert dets[2].back_views == seen  # from below it sees only the back of the board
