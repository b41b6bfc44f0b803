"""The prediction loop with a deterministic blob estimator: output schema, resume after a
kill, shards and merge, skipping finished outputs, and damaged inputs."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from predict_helpers import KEYPOINTS, BlobEstimator, h5_equal, make_session

from freipose.cli.main import cli
from freipose.io.calibration import load_calibration, save_calibration
from freipose.io.poses import read_poses_h5
from freipose.io.session import SessionError, discover_sessions
from freipose.io.video import MediaError, frame_range
from freipose.predict.merge import MergeError, merge_outputs, merge_shards
from freipose.predict.run import parse_shard, predict_session, shard_range
from freipose.predict.writer import STATUS_FEW_VIEWS, STATUS_NOT_FOUND, STATUS_OK, partial_path

N = 40


@pytest.fixture(scope="module")
def session_dir(tmp_path_factory) -> tuple[Path, np.ndarray]:
    folder = tmp_path_factory.mktemp("sessions") / "rec1"
    _, truth = make_session(folder, N, absent=(5, 6, 33))
    return folder, truth


@pytest.fixture(scope="module")
def reference(session_dir, tmp_path_factory) -> Path:
    """An uninterrupted run (batch 4, chunks of 8 rows)."""
    (s,) = discover_sessions([session_dir[0]])
    out = tmp_path_factory.mktemp("ref")
    res = predict_session(s, BlobEstimator(), out, batch_size=4, chunk_frames=8, progress=False)
    return res.path


class Killed(Exception):
    pass


def test_output_schema_and_accuracy(session_dir, reference):
    _, truth = session_dir
    d = read_poses_h5(reference)
    assert d.keypoints == KEYPOINTS
    assert d.poses.shape == (N, 2, 3)
    np.testing.assert_array_equal(d.frame_index, np.arange(N))
    assert d.fps == pytest.approx(25.0)
    assert d.calibration is not None and d.calibration.names == ["cam0", "cam1", "cam2", "cam3"]
    st = d.extra["status"]
    absent = np.array([5, 6, 33])
    assert np.all(st[absent] == STATUS_NOT_FOUND)
    assert np.all(np.isnan(d.poses[absent])) and np.all(d.confidence[absent] == 0)
    assert np.all(np.isnan(d.extra["center"][absent]))
    found = np.setdiff1d(np.arange(N), absent)
    assert np.all(st[found] == STATUS_OK)
    err = np.linalg.norm(d.poses[found] - truth[found], axis=-1)
    assert np.median(err) < 3.0 and err.max() < 10.0
    assert d.extra["points2d"].shape == (N, 4, 2, 2)
    assert d.extra["boxes"].shape == (N, 4, 4)
    assert d.extra["frame_ok"].all()
    assert d.provenance["model"] == "blob-test-estimator"
    assert d.provenance["videos"] == {f"cam{i}": f"cam{i}.mp4" for i in range(4)}
    with h5py.File(reference, "r") as f:
        assert f.attrs["complete"] and f.attrs["completed_frames"] == N
    assert not partial_path(reference).exists()


def test_kill_and_resume_equals_uninterrupted(session_dir, reference, tmp_path):
    (s,) = discover_sessions([session_dir[0]])

    def kill_after_20(rows: int) -> None:
        if rows >= 20:
            raise Killed

    est = BlobEstimator()
    with pytest.raises(Killed):
        predict_session(
            s, est, tmp_path, batch_size=4, chunk_frames=8, progress=False, on_batch=kill_after_20
        )
    out = tmp_path / "rec1.poses.h5"
    assert not out.exists()
    with h5py.File(partial_path(out), "r") as f:
        assert f.attrs["completed_frames"] == 16  # two whole chunks of 8 were committed
        assert not f.attrs["complete"]
    est2 = BlobEstimator()
    res = predict_session(s, est2, tmp_path, batch_size=4, chunk_frames=8, progress=False)
    assert res.frames == N - 16 and est2.frames == N - 16  # resumed, did not redo
    assert h5_equal(res.path, reference) == []
    # a second identical call skips the complete output
    res2 = predict_session(
        s, BlobEstimator(), tmp_path, batch_size=4, chunk_frames=8, progress=False
    )
    assert res2.skipped and res2.frames == 0
    # --overwrite redoes it
    est3 = BlobEstimator()
    res3 = predict_session(
        s, est3, tmp_path, batch_size=4, chunk_frames=8, overwrite=True, progress=False
    )
    assert not res3.skipped and est3.frames == N
    assert h5_equal(res3.path, reference) == []


def test_partial_from_other_settings_is_discarded(session_dir, tmp_path, caplog):
    (s,) = discover_sessions([session_dir[0]])

    def kill(rows: int) -> None:
        if rows >= 12:
            raise Killed

    with pytest.raises(Killed):
        predict_session(
            s,
            BlobEstimator(),
            tmp_path,
            frames="0:30",
            batch_size=4,
            chunk_frames=8,
            progress=False,
            on_batch=kill,
        )
    est = BlobEstimator()
    with caplog.at_level(logging.WARNING):
        res = predict_session(s, est, tmp_path, batch_size=4, chunk_frames=8, progress=False)
    assert "other settings" in caplog.text
    assert est.frames == N and read_poses_h5(res.path).num_frames == N


def test_damaged_partial_is_restarted(session_dir, reference, tmp_path):
    (s,) = discover_sessions([session_dir[0]])
    partial_path(tmp_path / "rec1.poses.h5").write_bytes(b"\x89HDF garbage from a killed write")
    res = predict_session(
        s, BlobEstimator(), tmp_path, batch_size=4, chunk_frames=8, progress=False
    )
    assert h5_equal(res.path, reference) == []


def test_shard_and_merge_equals_single_run(session_dir, reference, tmp_path):
    (s,) = discover_sessions([session_dir[0]])
    parts = []
    for i in range(3):
        r = predict_session(
            s, BlobEstimator(), tmp_path, batch_size=4, chunk_frames=8, shard=(i, 3), progress=False
        )
        parts.append(r.path)
        assert r.path.name == f"rec1.shard-{i}-of-3.poses.h5"
    lens = [read_poses_h5(p).num_frames for p in parts]
    assert sum(lens) == N and all(n % 8 == 0 for n in lens[:-1])
    with pytest.raises(MergeError, match="missing shards"):
        merge_shards(parts[:2], tmp_path / "x.poses.h5")
    (merged,) = merge_outputs([tmp_path], tmp_path / "merged")
    assert merged.name == "rec1.poses.h5"
    assert h5_equal(merged, reference) == []
    # the command: merge the folder's shards and remove them
    res = CliRunner().invoke(
        cli, ["merge", str(tmp_path), "-o", str(tmp_path / "m2"), "--remove-shards"]
    )
    assert res.exit_code == 0, res.output
    assert h5_equal(tmp_path / "m2" / "rec1.poses.h5", reference) == []
    assert not any(p.exists() for p in parts)
    res = CliRunner().invoke(cli, ["merge", str(tmp_path)])
    assert res.exit_code != 0 and "no shard files" in res.output


def test_shards_from_different_runs_refuse_to_merge(session_dir, tmp_path):
    (s,) = discover_sessions([session_dir[0]])
    a = predict_session(
        s,
        BlobEstimator(),
        tmp_path / "a",
        frames="0:32",
        batch_size=4,
        chunk_frames=8,
        shard=(0, 2),
        progress=False,
    ).path
    b = predict_session(
        s,
        BlobEstimator(),
        tmp_path / "b",
        batch_size=4,
        chunk_frames=8,
        shard=(1, 2),
        progress=False,
    ).path
    with pytest.raises(MergeError, match="different settings"):
        merge_shards([a, b], tmp_path / "m.poses.h5")


def test_frame_range_and_shard_parsing():
    assert frame_range("10:20", 100) == range(10, 20)
    assert frame_range(":5", 100) == range(0, 5)
    assert frame_range("90:", 100) == range(90, 100)
    assert frame_range(None, 7) == range(0, 7)
    with pytest.raises(ValueError, match="START:STOP"):
        frame_range("10", 100)
    with pytest.raises(ValueError, match="selects no frames"):
        frame_range("50:40", 100)
    assert parse_shard("2/4") == (2, 4)
    for bad in ("4/4", "x/2", "1", "-1/3"):
        with pytest.raises(ValueError):
            parse_shard(bad)
    ranges = [shard_range(3, 1003, (i, 4), 64) for i in range(4)]
    assert ranges[0][0] == 3 and ranges[-1][1] == 1003
    assert all(r[1] == q[0] for r, q in zip(ranges, ranges[1:]))
    assert all((r[0] - 3) % 64 == 0 for r in ranges)


def test_frames_option_writes_that_range(session_dir, reference, tmp_path):
    (s,) = discover_sessions([session_dir[0]])
    res = predict_session(
        s, BlobEstimator(), tmp_path, frames="8:24", batch_size=4, chunk_frames=8, progress=False
    )
    d, ref = read_poses_h5(res.path), read_poses_h5(reference)
    np.testing.assert_array_equal(d.frame_index, np.arange(8, 24))
    np.testing.assert_array_equal(d.poses, ref.poses[8:24])


# -- damaged and invalid inputs ------------------------------------------------------------


def test_truncated_video_processes_readable_part_and_reports_gap(tmp_path, caplog):
    folder = tmp_path / "trunc"
    _, truth = make_session(folder, N, suffix=".mkv")
    vid = folder / "cam2.mkv"
    data = vid.read_bytes()
    vid.write_bytes(data[: len(data) // 2])
    (s,) = discover_sessions([folder])
    with caplog.at_level(logging.WARNING):
        res = predict_session(
            s, BlobEstimator(), tmp_path / "out", batch_size=4, chunk_frames=8, progress=False
        )
    assert "cam2" in res.missing
    gap = res.missing["cam2"]
    assert 0 < gap < N
    assert "could not be decoded" in caplog.text and "cam2" in caplog.text
    d = read_poses_h5(res.path)
    ok = d.extra["frame_ok"]
    assert ok[:gap].all() and not ok[gap:, 2].any() and ok[gap:, [0, 1, 3]].all()
    # frames after the gap are predicted from the three remaining cameras
    assert np.all(d.extra["status"] == STATUS_OK)
    assert np.all(np.isnan(d.extra["points2d"][gap:, 2]))
    err = np.linalg.norm(d.poses - truth, axis=-1)
    assert np.median(err[gap:]) < 5.0


def test_too_few_views_hold_nan(tmp_path):
    folder = tmp_path / "two"
    make_session(folder, 16, n_cams=2, suffix=".mkv")
    vid = folder / "cam1.mkv"
    data = vid.read_bytes()
    vid.write_bytes(data[: len(data) // 2])
    (s,) = discover_sessions([folder])
    res = predict_session(s, BlobEstimator(), tmp_path / "out", batch_size=4, progress=False)
    d = read_poses_h5(res.path)
    gap = res.missing["cam1"]
    assert np.all(d.extra["status"][gap:] == STATUS_FEW_VIEWS)
    assert np.all(np.isnan(d.poses[gap:])) and np.all(d.confidence[gap:] == 0)
    assert res.status_counts["too few views"] == 16 - gap


def test_unopenable_video_fails_before_work(session_dir, tmp_path):
    folder = tmp_path / "bad"
    shutil.copytree(session_dir[0], folder)
    (folder / "cam1.mp4").write_bytes(b"this is not a video" * 100)
    with pytest.raises(MediaError, match="cam1"):
        discover_sessions([folder])


def test_camera_missing_from_calibration(session_dir, tmp_path):
    folder = tmp_path / "extra_cam"
    shutil.copytree(session_dir[0], folder)
    shutil.copy(folder / "cam0.mp4", folder / "side.mp4")
    with pytest.raises(SessionError, match=r"\['side'\].*not in the calibration"):
        discover_sessions([folder])


def test_wrong_image_size_and_different_lengths(session_dir, tmp_path, caplog):
    folder = tmp_path / "sizes"
    shutil.copytree(session_dir[0], folder)
    rig = load_calibration(folder / "calibration.toml")
    cam = rig["cam0"].replace(size=(320, 240))
    save_calibration(rig.__class__((cam, *rig.cameras[1:]), rig.metadata), tmp_path / "big.toml")
    with pytest.raises(SessionError, match="160x120.*320x240"):
        discover_sessions([folder], calibration=tmp_path / "big.toml")
    short = tmp_path / "short"
    make_session(short, 30)
    shutil.copy(short / "cam3.mp4", folder / "cam3.mp4")
    with caplog.at_level(logging.WARNING):
        (s,) = discover_sessions([folder])
    assert s.num_frames == 30 and "different lengths" in caplog.text


def test_explicit_video_list_and_calibration_cameras_without_video(session_dir, caplog):
    folder = session_dir[0]
    with caplog.at_level(logging.WARNING):
        (s,) = discover_sessions([folder / "cam0.mp4", folder / "cam2.mp4", folder / "cam3.mp4"])
    assert s.name == "rec1" and s.cameras == ["cam0", "cam2", "cam3"]
    assert "no video" in caplog.text
    with pytest.raises(SessionError, match="at least two"):
        discover_sessions([folder / "cam0.mp4"])
