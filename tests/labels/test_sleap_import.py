"""SLEAP import of per-camera files of predicted instances (sleap-anipose's layout).

The .slp files are written with sleap-io: one per camera in ``session/<camera>/``, with
predictions (scores) and a few user instances; the videos are symlinks into another
folder. Checks: the ``--instances`` choice and its record in the labels file, cameras from
the folders (or ``--camera-map``), the session's ``fps``, the video path as given, the
highest-scoring prediction, the folder's ``calibration.toml``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.io.calibration_toml import write_calibration_toml
from freipose.io.labels import read_labels_h5
from freipose.io.video import VideoWriter
from freipose.testing import make_circle_rig

sio = pytest.importorskip("sleap_io")

KPS = ["nose", "ear_left", "ear_right", "tail"]
FRAMES = [0, 3, 6, 9, 12]
FPS = 25.0


def _truth(n: int) -> np.ndarray:
    body = np.array([[40.0, 0, 30], [20, 12, 35], [20, -12, 35], [-50, 0, 10]])
    shift = np.arange(n)[:, None, None] * np.array([5.0, -3.0, 0.0])
    return body[None] + shift  # (n, K, 3)


def _session(tmp_path: Path, folders: list[str], with_user: bool = False):
    """A session folder ``sess/<folder>/<folder>.slp`` + symlinked video per camera."""
    rig = make_circle_rig(3, radius=600, height=400, size=(160, 120), focal=150)
    X = _truth(len(FRAMES))
    uv = rig.project(X)  # (n, C, K, 2)
    sess = tmp_path / "sess"
    store = tmp_path / "store"
    store.mkdir()
    sk = sio.Skeleton(KPS)
    for c, folder in enumerate(folders):
        d = sess / folder
        d.mkdir(parents=True)
        real = store / f"real_{c}.mkv"
        with VideoWriter(real, FPS, (160, 120)) as w:
            for _ in range(15):
                w.write(np.zeros((120, 160, 3), np.uint8))
        os.symlink(real, d / f"{folder}.mkv")
        video = sio.Video(filename=str(d / f"{folder}.mkv"), open_backend=False)
        lfs = []
        for i, f in enumerate(FRAMES):
            good = sio.PredictedInstance.from_numpy(
                uv[i, c], skeleton=sk, point_scores=np.full(len(KPS), 0.9), score=0.9
            )
            worse = sio.PredictedInstance.from_numpy(
                uv[i, c] + 30, skeleton=sk, point_scores=np.full(len(KPS), 0.2), score=0.2
            )
            insts = [worse, good]
            if with_user and i == 0:
                insts.append(sio.Instance.from_numpy(uv[i, c] + 4.0, skeleton=sk))
            lfs.append(sio.LabeledFrame(video=video, frame_idx=f, instances=insts))
        sio.save_slp(sio.Labels(labeled_frames=lfs), str(d / f"{folder}.slp"))
    return rig, X, sess


def _import(args: list[str]) -> tuple[int, str]:
    res = CliRunner().invoke(cli, ["labels", "import", "--format", "sleap", *args])
    return res.exit_code, res.output


def test_predicted_instances_from_camera_folders(tmp_path):
    rig, X, sess = _session(tmp_path, list(make_circle_rig(3).names))
    write_calibration_toml(rig, sess / "calibration.toml")
    out = tmp_path / "labels" / "labels.h5"
    code, msg = _import([str(sess), "-o", str(out)])
    assert code != 0 and "--instances predicted" in msg and "0 user-labeled" in msg
    assert not out.exists()
    code, msg = _import([str(sess), "--instances", "predicted", "-o", str(out)])
    assert code == 0, msg
    lab = read_labels_h5(out)
    assert list(lab.cameras) == ["cam0", "cam1", "cam2"]
    assert set(lab.session) == {"sess"}
    np.testing.assert_array_equal(lab.frame_index, FRAMES)
    # the highest-scoring prediction of each frame, triangulated with the folder's calibration
    np.testing.assert_allclose(lab.points3d, X, atol=1e-3)
    info = lab.sessions["sess"]
    assert info.instances == "predicted"
    assert info.fps == pytest.approx(FPS)
    # the symlink's path, relative to the labels file, not the link target in store/
    assert info.videos["cam1"] == os.path.join("..", "sess", "cam1", "cam1.mkv")


def test_all_prefers_user_instances_and_camera_map(tmp_path):
    rig, X, sess = _session(tmp_path, ["A", "B", "C"], with_user=True)
    cal = tmp_path / "calibration.toml"
    write_calibration_toml(rig, cal)
    out = tmp_path / "labels.h5"
    maps = ["--camera-map", "A=cam0", "--camera-map", "B=cam1", "--camera-map", "C=cam2"]
    code, msg = _import([str(sess), "--instances", "all", "--calibration", str(cal), *maps,
                         "-o", str(out)])  # fmt: skip
    assert code == 0, msg
    lab = read_labels_h5(out)
    assert lab.sessions["sess"].instances == "all"
    uv0 = rig.project(X[:1])[0]  # frame 0: the user instance (+4 px) replaces the predictions
    np.testing.assert_allclose(lab.points2d[0], uv0 + 4.0, atol=1e-6)
    np.testing.assert_allclose(lab.points2d[1:], rig.project(X[1:]), atol=1e-6)
    # --instances user: only frame 0 has a user instance
    code, msg = _import([str(sess), "--calibration", str(cal), *maps, "-o", str(out)])
    assert code == 0, msg
    lab = read_labels_h5(out)
    assert lab.sessions["sess"].instances == "user" and list(lab.frame_index) == [0]


def test_instances_only_for_sleap(tmp_path):
    res = CliRunner().invoke(
        cli,
        ["labels", "import", "--format", "dlc", str(tmp_path), "--instances", "all",
         "-o", str(tmp_path / "x.h5")],
    )  # fmt: skip
    assert res.exit_code != 0 and "--format sleap only" in res.output


def test_camera_folder_with_two_files_is_refused(tmp_path):
    _, _, sess = _session(tmp_path, ["cam0", "cam1"])
    (sess / "cam0" / "other.slp").write_bytes((sess / "cam0" / "cam0.slp").read_bytes())
    code, msg = _import([str(sess), "--instances", "predicted", "-o", str(tmp_path / "x.h5")])
    assert code != 0 and "2 .slp files" in msg and "cam0" in msg
