"""End to end: train_detector from a training TOML, `freipose detect`, and boxes.h5."""

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.detect.detector import load_checkpoint
from freipose.detect.train import DetectorTrainConfig, train_detector
from freipose.io.boxes import BoxesData, BoxesFormatError, read_boxes_h5, write_boxes_h5
from freipose.io.labels import read_labels_h5
from freipose.io.video import frame_range

TINY = {"input_size": 64, "width": 0.25, "neck_channels": 16, "batch_size": 8, "warmup_steps": 5}


def test_train_detector_from_config(session_dir, tmp_path, capsys):
    config = {
        "data": {"labels": "labels.h5"},
        "detector": {**TINY, "steps": 12, "eval_fraction": 0.25},
    }
    out = train_detector(config, session_dir / "train.toml", tmp_path / "run", False, "cpu")
    assert (
        out == tmp_path / "run" / "detector.pt"
        and (tmp_path / "run" / "detector_last.pt").is_file()
    )
    ckpt = load_checkpoint(out)
    m = ckpt["metrics"]
    for key in ("recall", "median_center_error", "cpu_fps", "n_instants"):
        assert key in m
    assert m["n_instants"] == 4  # a quarter of 16 frames held out
    assert m["n_views"] > 0 and m["cpu_fps"] > 0
    printed = capsys.readouterr().out
    assert (
        "recall@IoU0.5" in printed and "median 3D centre error" in printed and "frames/s" in printed
    )
    assert "3D centre found in" in printed and "of 4 time instants" in printed
    lab = read_labels_h5(session_dir / "labels.h5")  # the speed is measured at the videos' size
    w, h = next(iter(lab.sessions.values())).calibration[0].size
    assert f"CPU ({w}x{h} images, as the training videos;" in printed


def test_train_config_errors(session_dir, tmp_path):
    with pytest.raises(ValueError, match="unknown keys"):
        DetectorTrainConfig.from_dict({"stepz": 3})
    with pytest.raises(ValueError, match=r"\[data\] table"):
        train_detector({"detector": TINY}, session_dir / "t.toml", tmp_path, False, "cpu")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        train_detector(
            {"data": {"labels": "nope.h5"}}, session_dir / "t.toml", tmp_path, False, "cpu"
        )


def test_cli_detect_bgsub_and_fixed(session_dir, tmp_path):
    runner = CliRunner()
    out = tmp_path / "boxes.h5"
    res = runner.invoke(cli, ["detect", str(session_dir), "--method", "bgsub", "-o", str(out)])
    assert res.exit_code == 0, res.output
    data = read_boxes_h5(out)
    assert len(data) == 16 and data.cameras == ("cam0", "cam1", "cam2", "cam3")
    assert data.method == "bgsub" and data.cube_size == 400.0
    assert (data.n_agree == 4).all() and data.agree.all()
    from freipose.io.labels import read_labels_h5

    truth = read_labels_h5(session_dir / "labels.h5").points3d.mean(1)  # the body centre
    assert np.median(np.linalg.norm(data.center - truth, axis=1)) < 15.0
    assert data.calibration is not None and data.calibration.names == list(data.cameras)

    # Fixed boxes around the image centres, a frame range.
    (tmp_path / "fixed.toml").write_text(
        "[boxes]\n" + "".join(f"cam{i} = [39.5, 29.5, 119.5, 89.5]\n" for i in range(4))
    )
    fixed = str(tmp_path / "fixed.toml")
    res = runner.invoke(
        cli,
        ["detect", str(session_dir), "--fixed-boxes", fixed, "--frames", "2:6", "-o", str(out),
         "--overwrite"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    data = read_boxes_h5(out)
    assert list(data.frame_index) == [2, 3, 4, 5] and data.method == "fixed"
    # Boxes centred on the principal points: their rays meet at the look-at point, the origin.
    assert np.allclose(data.center, 0.0, atol=1.0)


def test_cli_detect_model_and_errors(session_dir, tmp_path):
    config = {
        "data": {"labels": "labels.h5"},
        "detector": {**TINY, "steps": 2, "eval_fraction": 0.0},
    }
    ckpt = train_detector(config, session_dir / "train.toml", tmp_path / "run", False, "cpu")
    runner = CliRunner()
    out = tmp_path / "b.h5"
    res = runner.invoke(cli, ["detect", str(session_dir), "--model", str(ckpt), "--device", "cpu",
                              "--frames", ":3", "-o", str(out)])  # fmt: skip
    assert res.exit_code == 0, res.output
    data = read_boxes_h5(out)
    assert data.boxes.shape == (3, 4, 4) and data.method == "detector"
    res = runner.invoke(cli, ["detect", str(session_dir), "-o", str(out)])
    assert res.exit_code != 0 and "--method bgsub" in res.output
    res = runner.invoke(cli, ["detect", str(session_dir), "--method", "bgsub", "--frames", "9:2",
                              "-o", str(out)])  # fmt: skip
    assert res.exit_code != 0 and "selects no frame" in res.output
    res = runner.invoke(cli, ["detect", str(tmp_path), "--method", "bgsub", "-o", str(out)])
    assert res.exit_code != 0 and "calibration not found" in res.output


def test_parse_frames():
    assert frame_range(None, 5) == range(5)
    assert frame_range("1:3", 10) == range(1, 3)
    assert frame_range("-2:", 10) == range(8, 10)
    with pytest.raises(ValueError, match="START:STOP"):
        frame_range("5", 10)


def test_boxes_h5_round_trip_and_errors(tmp_path, circle_rig):
    t, c = 3, len(circle_rig)
    data = BoxesData(
        frame_index=np.arange(t) + 10, cameras=tuple(circle_rig.names),
        boxes=np.random.default_rng(0).uniform(0, 100, (t, c, 4)), scores=np.full((t, c), 0.5),
        agree=np.ones((t, c), bool), n_agree=np.full(t, c), center=np.zeros((t, 3)),
        crop_boxes=np.full((t, c, 4), np.nan), cube_size=300, method="detector",
        calibration=circle_rig, attrs={"source": "x.pt"},
    )  # fmt: skip
    write_boxes_h5(data, tmp_path / "b.h5")
    back = read_boxes_h5(tmp_path / "b.h5")
    np.testing.assert_allclose(back.boxes, data.boxes)
    assert back.calibration.allclose(circle_rig) and back.attrs["source"] == "x.pt"
    assert back.cube_size == 300.0 and list(back.frame_index) == [10, 11, 12]
    with pytest.raises(ValueError, match="shape"):
        BoxesData(np.arange(2), ("a",), np.zeros((2, 1, 3)), np.zeros((2, 1)),
                  np.ones((2, 1), bool), np.ones(2), np.zeros((2, 3)), np.zeros((2, 1, 4)), 1.0,
                  "x")  # fmt: skip
    with h5py.File(tmp_path / "x.h5", "w") as f:
        f.attrs["schema"] = "freipose.poses"
    with pytest.raises(BoxesFormatError, match="expected a FreiPose boxes file"):
        read_boxes_h5(tmp_path / "x.h5")
    with pytest.raises(FileNotFoundError):
        read_boxes_h5(tmp_path / "missing.h5")


def test_detect_session_resumes_after_interruption(session_dir, tmp_path):
    from freipose.detect import FixedBoxes
    from freipose.detect.pipeline import detect_session, open_sources
    from freipose.io.session import discover_sessions

    session = discover_sessions([session_dir], cameras="calibration", need_fps=False)[0]
    rig, sources, n = session.rig, open_sources(session), session.num_frames
    boxes = {c: [39.5 + i, 29.5, 119.5 + i, 89.5] for i, c in enumerate(rig.names)}

    class Flaky(FixedBoxes):
        calls = 0

        def propose(self, images, cameras):
            Flaky.calls += 1
            if Flaky.calls == 4:
                raise RuntimeError("interrupted")
            return super().propose(images, cameras)

    progress = tmp_path / "p.npz"
    with pytest.raises(RuntimeError, match="interrupted"):
        detect_session(rig, sources, range(n), Flaky(boxes), batch_size=2, method="fixed",
                       progress_file=progress, save_every=4)  # fmt: skip
    assert progress.is_file()
    with np.load(progress) as z:
        assert int(z["done"]) == 4  # saved after 4 frames; the 4th batch (frames 6, 7) failed
    calls_before = Flaky.calls
    resumed = detect_session(rig, sources, range(n), Flaky(boxes), batch_size=2, method="fixed",
                             progress_file=progress, save_every=4)  # fmt: skip
    assert Flaky.calls - calls_before == (n - 4) // 2  # only the remaining batches ran
    full = detect_session(rig, sources, range(n), FixedBoxes(boxes), batch_size=2, method="fixed")
    np.testing.assert_allclose(resumed.center, full.center)
    np.testing.assert_array_equal(resumed.n_agree, full.n_agree)
    # Other settings do not reuse the progress file.
    other = detect_session(rig, sources, range(n), FixedBoxes(boxes), batch_size=2,
                           method="other", progress_file=progress)  # fmt: skip
    np.testing.assert_allclose(other.center, full.center)


def test_camera_map_names_videos_that_are_not_named_after_their_cameras(session_dir, tmp_path):
    from freipose.io.session import SessionError, discover_sessions

    # a SLEAP-style folder: min_session_<camera>.mp4 next to the calibration
    folder = tmp_path / "renamed"
    folder.mkdir()
    for f in session_dir.iterdir():
        name = f"min_session_{f.name}" if f.suffix == ".mkv" else f.name
        (folder / name).symlink_to(f.resolve())
    cams = ("cam0", "cam1", "cam2", "cam3")
    runner = CliRunner()
    out = tmp_path / "boxes.h5"
    res = runner.invoke(cli, ["detect", str(folder), "--method", "bgsub", "-o", str(out)])
    assert res.exit_code != 0 and "--camera-map VIDEO_STEM=CAMERA" in res.output
    maps = [a for c in cams for a in ("--camera-map", f"min_session_{c}={c}")]
    res = runner.invoke(cli, ["detect", str(folder), "--method", "bgsub", "-o", str(out), *maps])
    assert res.exit_code == 0, res.output
    assert read_boxes_h5(out).cameras == cams
    s = discover_sessions([folder], camera_map={f"min_session_{c}": c for c in cams})[0]
    assert tuple(s.cameras) == cams and s.videos["cam2"].name == "min_session_cam2.mkv"
    with pytest.raises(SessionError, match="not video file stems"):
        discover_sessions([folder], camera_map={"nope": "cam0"})
    with pytest.raises(SessionError, match="two videos for camera 'cam0'"):
        discover_sessions(
            [folder], camera_map={"min_session_cam1": "cam0", "min_session_cam0": "cam0"}
        )
