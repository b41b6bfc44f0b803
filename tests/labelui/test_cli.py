"""``freipose label``: start-up refusals, resume, predictions, the running command, round trip."""

from __future__ import annotations

import re
import shutil
import signal
import subprocess
import sys
import time

import httpx
import numpy as np
from click.testing import CliRunner
from starlette.testclient import TestClient

from freipose.cli.label import label as label_cmd
from freipose.cli.labels_select import select as select_cmd
from freipose.cli.main import cli
from freipose.io.calibration import load_calibration, save_calibration
from freipose.io.labels import read_labels_h5
from freipose.io.lock import lock_path
from freipose.labelui.app import create_app
from freipose.labelui.frames import FrameCache
from freipose.labelui.geometry import OCCLUDED, VISIBLE
from freipose.labelui.startup import open_store

H = {"X-FreiPose-Token": "t0k3n"}


def _run(args: list[str]):
    return CliRunner().invoke(label_cmd, [str(a) for a in args] + ["--no-browser"])


def test_startup_refusals_before_any_server(synth_session, tmp_path):
    s = synth_session
    base = [s.folder, "--calibration", s.calibration, "--skeleton", "rat"]
    # a calibration without one of the session's cameras
    rig = load_calibration(s.calibration)
    save_calibration(rig.subset(["cam0", "cam1"]), tmp_path / "two.toml")
    res = _run([s.folder, "--calibration", tmp_path / "two.toml", "--skeleton", "rat",
                "-o", tmp_path / "a.h5"])  # fmt: skip
    assert (
        res.exit_code == 1
        and "not in the calibration" in res.output
        and "--calibration" in res.output
    )
    # an unreadable video
    bad = tmp_path / "rat1"
    shutil.copytree(s.folder, bad)
    (bad / "cam2.mp4").write_bytes(b"not a video at all")
    res = _run([bad, "--calibration", s.calibration, "--skeleton", "rat", "-o", tmp_path / "b.h5"])
    assert res.exit_code == 1 and "cam2" in res.output and "cannot open" in res.output
    # a skeleton that does not match the existing labels file
    store = open_store([s.folder], s.calibration, "rat", tmp_path / "c.h5", per_session=2)
    store.write()
    res = _run(base + ["--skeleton", "mouse", "-o", tmp_path / "c.h5"])
    assert res.exit_code == 1 and "differ from the skeleton 'mouse'" in res.output
    # a frame list of other sessions or frames
    (tmp_path / "sel.csv").write_text("session,frame_index\nrat2,3\n")
    res = _run(base + ["--frames", tmp_path / "sel.csv", "-o", tmp_path / "d.h5"])
    assert res.exit_code == 1 and "'rat2'" in res.output and "--frames" in res.output
    (tmp_path / "sel.csv").write_text("session,frame_index\nrat1,12\n")
    res = _run(base + ["--frames", tmp_path / "sel.csv", "-o", tmp_path / "d.h5"])
    assert res.exit_code == 1 and "outside the videos" in res.output
    assert not (tmp_path / "d.h5").exists() and not lock_path(tmp_path / "d.h5").exists()
    # animals named twice
    res = _run(base + ["--animals", "resident,resident", "-o", tmp_path / "e.h5"])
    assert res.exit_code == 1 and "distinct names" in res.output and "Traceback" not in res.output


def test_resume_keeps_states_and_other_sessions(synth_session, tmp_path):
    s = synth_session
    out = tmp_path / "labels.h5"
    store = open_store([s.folder], s.calibration, "rat", out, per_session=3)
    V, K = 3, 12
    pts = np.full((V, K, 2), np.nan)
    status = np.zeros((V, K), np.int8)
    pts[0, 2], status[0, 2] = (100.0, 80.0), VISIBLE
    status[1, 2] = OCCLUDED
    store.save(1, 0, pts, status)
    again = open_store([s.folder], s.calibration, "rat", out, per_session=3)
    st = again.state(1)
    assert st["labels"]["cam0"]["Paw Front Right"] == {"state": "visible", "x": 100.0, "y": 80.0}
    assert st["labels"]["cam1"]["Paw Front Right"] == {"state": "occluded"}
    assert again.progress()["labeled"] == 1
    # a resumed frame that is not among the evenly spread instants is appended
    again.save(2, 0, pts, status)
    third = open_store([s.folder], s.calibration, "rat", out, per_session=2)
    assert [(x.session, x.frame) for x in third.instants] == [
        ("rat1", 0),
        ("rat1", 11),
        ("rat1", 6),
    ]
    # labels of a session this run does not edit are kept
    ls = read_labels_h5(out)
    other = tmp_path / "other"
    shutil.copytree(s.folder, other)
    store2 = open_store([other], s.calibration, "rat", out, per_session=1)
    store2.save(0, 0, pts, status)
    ls2 = read_labels_h5(out)
    assert sorted(set(ls2.session)) == ["other", "rat1"] and len(ls2) == len(ls) + 1
    np.testing.assert_array_equal(ls2.points2d[: len(ls)], ls.points2d)


def test_predictions_prefill_but_are_never_written(synth_session, tmp_path, poses_dir):
    s = synth_session
    poses = poses_dir
    store = open_store([s.folder], s.calibration, "rat", tmp_path / "l.h5", poses_dir=poses,
                       per_session=3)  # fmt: skip
    assert [round(x.confidence, 2) for x in store.instants] == [0.9, 0.1, 0.9]
    st = store.state(0)
    rig = store.session(0).rig
    want = rig.project(s.truth.points3d[0] + 2.0)  # (V, K, 2)
    np.testing.assert_allclose(st["predicted"]["cam1"]["Nose"], want[1, 10], atol=2e-3)
    store.write()
    assert len(read_labels_h5(tmp_path / "l.h5")) == 0  # unconfirmed predictions: no labels


def test_select_label_train_round_trip(synth_session, tmp_path, poses_dir):
    """labels select -> label (through the HTTP API) -> train with the tiny preset."""
    s = synth_session
    poses = poses_dir
    sel = tmp_path / "selection.csv"
    args = [s.folder, "--calibration", s.calibration, "--poses-dir", poses, "--n", "4",
            "--min-gap", "1", "-o", sel]  # fmt: skip
    res = CliRunner().invoke(select_cmd, [str(a) for a in args])
    assert res.exit_code == 0, res.output
    out = tmp_path / "labels.h5"
    store = open_store([s.folder], s.calibration, "rat", out, frames=sel, poses_dir=poses)
    assert store.instants[0].frame == 6  # the least confident first
    frames = FrameCache(store.sessions, store.instants)
    t = s.truth
    with TestClient(create_app(store, frames, "t0k3n")) as client:
        for i, x in enumerate(store.instants):
            labels = {cam: {kp: {"state": "visible", "x": float(p[0]), "y": float(p[1])}
                            for kp, p, ok in zip(t.keypoints, t.points2d[x.frame, v],
                                                 t.visible2d[x.frame, v]) if ok}
                      for v, cam in enumerate(t.cameras)}  # fmt: skip
            r = client.post(f"/api/instant/{i}", json={"version": 0, "labels": labels}, headers=H)
            assert r.status_code == 200, r.text
    frames.close()
    ls = read_labels_h5(out)
    assert len(ls) == 4 and set(ls.frame_index) == set(store.instants[i].frame for i in range(4))
    err = np.linalg.norm(ls.points3d - t.points3d[ls.frame_index], axis=-1)
    assert np.nanmedian(err) < 1.0  # mm: labels at the true projections triangulate to the truth
    cfg = tmp_path / "train.toml"
    cfg.write_text(f'[data]\nlabels = "{out}"\nskeleton = "rat"\n[model]\npreset = "tiny"\n'
                   "[schedule]\nsteps = 2\nbatch_size = 2\n")  # fmt: skip
    res = CliRunner().invoke(cli, ["train", str(cfg), "--out", str(tmp_path / "run")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "run" / "model.pt").is_file()


def test_command_prints_url_serves_with_token_and_stops(synth_session, tmp_path):
    s = synth_session
    out = tmp_path / "labels.h5"
    proc = subprocess.Popen(
        [sys.executable, "-m", "freipose.cli.main", "label", str(s.folder), "--calibration",
         str(s.calibration), "--skeleton", "rat", "-o", str(out), "--port", "0", "--no-browser"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        url = None
        end = time.monotonic() + 30
        lines = []
        while url is None and time.monotonic() < end:
            line = proc.stdout.readline()
            lines.append(line)
            m = re.search(r"open (http://127\.0\.0\.1:(\d+)/\?token=([\w-]+))", line)
            if m:
                url, port, token = m.group(1), int(m.group(2)), m.group(3)
        assert url is not None, "".join(lines)
        assert len(token) >= 24 and port > 0
        assert httpx.get(f"http://127.0.0.1:{port}/api/config").status_code == 403
        r = httpx.get(url)
        assert r.status_code == 200 and "FreiPose label" in r.text
        assert httpx.get(f"http://127.0.0.1:{port}/api/progress", cookies=r.cookies).json()[
            "total"] == 12  # fmt: skip
        assert lock_path(out).exists()
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=20)
    assert not lock_path(out).exists()
