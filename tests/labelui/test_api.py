"""The labeling server's HTTP API via Starlette's test client: load, save, geometry, refusals."""

from __future__ import annotations

import json
from collections.abc import Iterator

import cv2
import numpy as np
import pytest
from starlette.testclient import TestClient

from freipose.geometry.triangulation import triangulate_weighted
from freipose.io.labels import read_labels_h5
from freipose.io.lock import OutputLockedError
from freipose.io.video import FrameSource
from freipose.labelui.app import COOKIE, create_app
from freipose.labelui.frames import FrameCache
from freipose.labelui.geometry import instant_geometry
from freipose.labelui.schema import MAX_BODY_BYTES
from freipose.labelui.server import serving
from freipose.labelui.store import LabelStore

TOKEN = "test-token-123"
H = {"X-FreiPose-Token": TOKEN}


@pytest.fixture
def client(store: LabelStore) -> Iterator[TestClient]:
    frames = FrameCache(store.sessions, store.instants)
    try:
        with TestClient(create_app(store, frames, TOKEN)) as c:
            yield c
    finally:
        frames.close()


def _truth_2d(synth_session, frame: int, cam: str, kp: str) -> np.ndarray:
    t = synth_session.truth
    return t.points2d[frame, t.cameras.index(cam), t.keypoints.index(kp)]


def _save(client, i, version, labels, **kw):
    return client.post(f"/api/instant/{i}", json={"version": version, "labels": labels},
                       headers=H, **kw)  # fmt: skip


def test_token_refused_without_and_accepted_three_ways(client):
    for path in ("/", "/api/config", "/api/instant/0", "/api/frame/0/cam0", "/static/label.js"):
        r = client.get(path)
        assert r.status_code == 403 and "token" in r.text
    assert client.get("/api/config", headers={"X-FreiPose-Token": "wrong"}).status_code == 403
    assert client.get("/api/config?token=wrong").status_code == 403
    assert client.get("/api/config", headers=H).status_code == 200
    page = client.get(f"/?token={TOKEN}")
    assert page.status_code == 200 and "label.js" in page.text
    assert page.cookies.get(COOKIE) == TOKEN  # the page sets the cookie ...
    assert client.get("/api/config").status_code == 200  # ... that later requests carry
    client.cookies.clear()
    assert client.get("/api/config").status_code == 403


def test_load_instant_and_its_frames(client, store, synth_session):
    cfg = client.get("/api/config", headers=H).json()
    assert cfg["keypoints"] == list(store.skeleton.keypoints)
    assert [x["frame"] for x in cfg["instants"]] == [0, 4, 7, 11]
    st = client.get("/api/instant/1", headers=H).json()
    assert st["frame"] == 4 and st["version"] == 0 and st["cameras"] == ["cam0", "cam1", "cam2"]
    assert st["labels"] == {"cam0": {}, "cam1": {}, "cam2": {}} and st["points3d"] == {}
    r = client.get("/api/frame/1/cam2", headers=H)
    assert r.status_code == 200 and r.headers["content-type"] == "image/jpeg"
    img = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_COLOR)
    with FrameSource(synth_session.folder / "cam2.mp4") as src:
        want = src.read(4).astype(float)
    assert img.shape == (256, 320, 3) and np.abs(img - want).mean() < 3  # JPEG of that frame


def test_save_triangulates_projects_and_writes_labels_h5(client, store, synth_session, tmp_path):
    kp = "Nose"
    a, b = (_truth_2d(synth_session, 7, c, kp) for c in ("cam0", "cam1"))
    labels = {"cam0": {kp: {"state": "visible", "x": float(a[0]), "y": float(a[1])}},
              "cam1": {kp: {"state": "visible", "x": float(b[0]), "y": float(b[1])}},
              "cam2": {"Tail": {"state": "occluded"}}}  # fmt: skip
    r = _save(client, 2, 0, labels)
    assert r.status_code == 200, r.text
    st = r.json()
    assert st["version"] == 1
    rig = store.session(2).rig
    obs = np.full((3, 2), np.nan)
    obs[0], obs[1] = a, b
    X = triangulate_weighted(obs, np.array([1.0, 1.0, 0.0]), rig)
    np.testing.assert_allclose(st["points3d"][kp], X, atol=2e-3)
    true3d = synth_session.truth.points3d[7, synth_session.truth.keypoints.index(kp)]
    assert np.linalg.norm(np.array(st["points3d"][kp]) - true3d) < 0.5  # mm
    proj = rig.project(X[None], distort=True)[2, 0]
    np.testing.assert_allclose(st["projected"]["cam2"][kp], proj, atol=2e-3)
    np.testing.assert_allclose(proj, _truth_2d(synth_session, 7, "cam2", kp), atol=0.05)
    assert st["residuals"]["cam0"][kp] < 0.01 and kp not in st["residuals"]["cam2"]
    assert st["progress"]["labeled"] == 1 and st["progress"]["done"][2]
    # a reload (another tab) sees the same state
    again = client.get("/api/instant/2", headers=H).json()
    assert again["labels"] == st["labels"] and again["version"] == 1
    assert again["labels"]["cam2"] == {"Tail": {"state": "occluded"}}
    # the file: labels.h5 format, only the labeled instant, visible labels and their 3D point
    ls = read_labels_h5(tmp_path / "labels.h5")
    assert list(ls.session) == ["rat1"] and list(ls.frame_index) == [7]
    k = ls.keypoints.index(kp)
    np.testing.assert_allclose(ls.points2d[0, :2, k], [a, b])
    assert np.isnan(ls.points2d[0, 2]).all() and not ls.visible2d[0, 2].any()
    np.testing.assert_allclose(ls.points3d[0, k], X, atol=1e-9)
    info = ls.sessions["rat1"]
    assert (
        info.calibration is not None
        and (tmp_path / info.videos["cam0"]).resolve()
        == (synth_session.folder / "cam0.mp4").resolve()
    )


def test_stale_version_conflict_409(client):
    lab = {"cam0": {"Tail": {"state": "visible", "x": 10.0, "y": 20.0}}}
    assert _save(client, 0, 0, lab).status_code == 200
    other = {"cam1": {"Tail": {"state": "notinview"}}}
    r = _save(client, 0, 0, other)  # a second tab still on version 0
    assert r.status_code == 409
    cur = r.json()["current"]
    assert cur["version"] == 1 and cur["labels"]["cam0"]["Tail"]["x"] == 10.0
    assert client.get("/api/instant/0", headers=H).json()["labels"]["cam1"] == {}  # not lost
    assert _save(client, 0, 1, other).status_code == 200  # on the current version it saves


@pytest.mark.parametrize(
    ("body", "needle"),
    [
        ({"version": 0, "labels": {"camX": {}}}, "unknown camera"),
        ({"version": 0, "labels": {"cam0": {"Trunk": {"state": "occluded"}}}}, "unknown keypoint"),
        ({"version": 0, "labels": {"cam0": {"Tail": {"state": "visible", "x": 320.0, "y": 5}}}},
         "outside the 320x256 image"),
        ({"version": 0, "labels": {"cam0": {"Tail": {"state": "visible", "x": 1, "y": -0.6}}}},
         "outside"),
        ({"version": 0, "labels": {"cam0": {"Tail": {"state": "visible", "x": "1", "y": 2}}}},
         "must be a number"),
        ({"version": 0, "labels": {"cam0": {"Tail": {"state": "occluded", "x": 1, "y": 2}}}},
         "no coordinates"),
        ({"version": 0, "labels": {"cam0": {"Tail": {"state": "hidden"}}}}, "state must be"),
        ({"version": True, "labels": {}}, "version must be"),
        ({"version": 0, "labels": [], "path": "/etc/passwd"}, "unknown fields"),
        ([1, 2], "JSON object"),
        ({"version": 0, "labels": {"cam0": {"Tail": {"state": [1]}}}}, "state must be"),
        ({"version": 0, "labels": {"cam0": {"Tail": {"state": {"a": 1}}}}}, "state must be"),
        ({"version": 0, "labels": {"cam0": {"Tail": {"state": "visible", "x": 10**400, "y": 1}}}},
         "must be finite"),
        ({"version": [0], "labels": {}}, "version must be"),
    ],
)  # fmt: skip
def test_bad_bodies_rejected_422(client, body, needle, tmp_path):
    r = client.post("/api/instant/0", json=body, headers=H)
    assert r.status_code == 422 and needle in r.json()["error"], r.text
    assert not (tmp_path / "labels.h5").exists()


def test_deeply_nested_bodies_rejected_422(client, tmp_path):
    deep = b"[" * 30_000 + b"]" * 30_000  # 60 KB, within the size limit
    r = client.post("/api/instant/0", content=deep, headers=H)
    assert r.status_code == 422 and "nests too deeply" in r.json()["error"], r.text
    inner: object = 0
    for _ in range(500):  # deep, but within what the decoder takes: the schema refuses it
        inner = {"a": inner}
    body = {"version": 0, "labels": {"cam0": {"Tail": inner}}}
    r = client.post("/api/instant/0", json=body, headers=H)
    assert r.status_code == 422 and "unknown fields" in r.json()["error"], r.text
    assert len(r.json()["error"]) < 300  # the message shows the value cut short
    assert not (tmp_path / "labels.h5").exists()


def test_bad_json_oversize_and_unknown_instants(client):
    r = client.post("/api/instant/0", content=b"{not json", headers=H)
    assert r.status_code == 422
    big = json.dumps({"version": 0, "labels": {}, "pad": "x" * MAX_BODY_BYTES}).encode()
    assert client.post("/api/instant/0", content=big, headers=H).status_code == 413

    def chunks():  # no Content-Length: the streamed size is limited too
        for _ in range(5):
            yield b" " * (MAX_BODY_BYTES // 4)

    assert client.post("/api/instant/0", content=chunks(), headers=H).status_code == 413
    for path in ("/api/instant/4", "/api/instant/-1", "/api/instant/abc", "/api/frame/9/cam0"):
        assert client.get(path, headers=H).status_code == 404, path


@pytest.mark.parametrize(
    "path",
    [
        "/api/frame/0/..%2F..%2Fcalibration.toml",
        "/api/frame/0/..%2Fcam0",
        "/api/frame/0/%2Fetc%2Fpasswd",
        "/api/frame/0/cam0.mp4",
        "/static/..%2Fstore.py",
        "/static/../app.py",
        "/static/%2E%2E/app.py",
        "/static/index.html",
        "/../../etc/passwd",
    ],
)
def test_path_traversal_refused(client, path):
    r = client.get(path, headers=H)
    assert r.status_code == 404, (path, r.status_code)
    assert b"import" not in r.content and b"root:" not in r.content


def test_second_server_on_the_same_labels_file_refused(store):
    with serving(store) as (running, _):
        assert running.url.startswith(f"http://127.0.0.1:{running.port}/?token=")
        assert running.port > 0 and len(running.token) >= 24
        with pytest.raises(OutputLockedError, match="another run"), serving(store):
            pass


def test_residuals_and_bone_lengths_flagged(store, synth_session):
    t = synth_session.truth
    rig = store.session(0).rig
    skel = store.skeleton
    ear, nose = t.keypoints.index("Ear Left"), t.keypoints.index("Nose")
    for i, x in enumerate(store.instants):
        pts = t.points2d[x.frame].copy()
        vis = t.visible2d[x.frame].copy()
        if i == 3:  # the left ear 30 mm up in 3D, the nose 12 px off in one view
            X = t.points3d[x.frame, ear] + [0.0, 0.0, 30.0]
            pts[:, ear] = rig.project(X[None])[:, 0]
            vis[:, [ear, nose]] = True
            pts[0, nose] += [12.0, 0.0]
        status = np.where(vis, 1, 0).astype(np.int8)
        state = store.save(i, 0, np.where(vis[..., None], pts, np.nan), status)
    assert state["residuals"]["cam0"]["Nose"] > store.settings.max_residual
    assert state["residuals"]["cam1"]["Ear Left"] < 0.01
    flagged = {b["limb"] for b in state["bones"] if b["flag"]}
    ear_ear = skel.limbs.index(((skel.index("Ear Right"),), (ear,)))
    moved = {n for n, (a, b) in enumerate(skel.limbs) if {ear, nose} & set(a + b)}
    assert ear_ear in flagged and flagged <= moved  # only limbs at the moved keypoints
    assert not any(b["flag"] for b in store.state(0)["bones"])  # the true poses are fine


def test_edits_recompute_only_changed_keypoints_same_result(store, synth_session):
    t = synth_session.truth
    x = store.instants[2]
    rig = store.session(2).rig
    vis = t.visible2d[x.frame]
    pts = np.where(vis[..., None], t.points2d[x.frame], np.nan)
    status = vis.astype(np.int8)
    store.save(2, 0, pts, status)
    pts2 = pts.copy()
    pts2[0, :4] += 1.5  # four keypoints move in cam0 ...
    status2 = status.copy()
    status2[1, 0] = 2  # ... and one becomes occluded in cam1
    st = store.save(2, 1, pts2, status2)
    full = instant_geometry(np.where((status2 == 1)[..., None], pts2, np.nan), status2, rig)
    for k, kp in enumerate(t.keypoints):
        if np.isfinite(full.points3d[k]).all():
            np.testing.assert_allclose(st["points3d"][kp], full.points3d[k], atol=2e-3)
        else:
            assert kp not in st["points3d"]
    st3 = store.save(2, 2, pts2, status2)  # no change: the same geometry
    assert st3["points3d"] == st["points3d"] and st3["version"] == 3
