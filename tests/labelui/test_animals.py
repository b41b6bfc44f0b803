"""Labeling several animals per instant: one labeling unit per animal, rows with ``individual``.

On a rendered two-rat session: each animal is labeled on its own and triangulated on its
own, the labels file gets a row per animal and frame, the state of one animal shows the
other's labels, predictions with an animal axis pre-fill each animal, a resumed run keeps
the animals, and a run that would mix one-animal and per-animal rows is refused.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np
import pytest
from starlette.testclient import TestClient

from freipose.io.labels import read_labels_h5
from freipose.io.poses import PoseData, write_poses_h5
from freipose.labelui.app import create_app
from freipose.labelui.frames import FrameCache
from freipose.labelui.schema import parse_body
from freipose.labelui.startup import LabelStartError, open_store, parse_animals
from freipose.labelui.store import LabelStore

TOKEN = "animals-token"
H = {"X-FreiPose-Token": TOKEN}


def _store(pair, output: Path, **kw) -> LabelStore:
    folder, calib, _ = pair
    return open_store([folder], calib, "rat", output, per_session=2, **kw)


@pytest.fixture
def client(pair, tmp_path: Path) -> Iterator[tuple[TestClient, LabelStore]]:
    store = _store(pair, tmp_path / "labels.h5", animals=("animal0", "animal1"))
    frames = FrameCache(store.sessions, store.instants)
    try:
        with TestClient(create_app(store, frames, TOKEN)) as c:
            yield c, store
    finally:
        frames.close()


def _truth(pair, frame: int, animal: str) -> int:
    t = pair[2]
    return int(np.flatnonzero((t.frame_index == frame) & (t.individual == animal))[0])


def _labels_of(pair, row: int, keypoints: list[int]) -> dict:
    """Body of a save: the true 2D points of ``keypoints`` in every view where visible."""
    t = pair[2]
    out: dict = {}
    for c, cam in enumerate(t.cameras):
        out[cam] = {
            t.keypoints[k]: {
                "state": "visible",
                "x": float(t.points2d[row, c, k, 0]),
                "y": float(t.points2d[row, c, k, 1]),
            }  # fmt: skip
            for k in keypoints
            if t.visible2d[row, c, k]
        }
    return out


def test_parse_animals() -> None:
    assert parse_animals("2") == ("animal_0", "animal_1")  # as freipose predict names them
    assert parse_animals("1") == ()
    assert parse_animals(" resident, intruder ") == ("resident", "intruder")
    for bad in ("0", "a,,b", "a,a"):
        with pytest.raises(LabelStartError, match="--animals"):
            parse_animals(bad)


def test_each_animal_labeled_and_triangulated_on_its_own(client, pair) -> None:
    c, store = client
    cfg = c.get("/api/config", headers=H).json()
    assert cfg["animals"] == ["animal0", "animal1"]
    units = [(x["frame"], x["individual"]) for x in cfg["instants"]]
    f0 = units[0][0]
    assert units[:2] == [(f0, "animal0"), (f0, "animal1")]  # the animals of a frame together
    assert len(units) == 2 * len({f for f, _ in units})
    st0 = c.get("/api/instant/0", headers=H).json()
    assert st0["individual"] == "animal0" and st0["others"] == {}
    assert [(a["index"], a["name"], a["labeled"]) for a in st0["animals"]] == [
        (0, "animal0", False), (1, "animal1", False)]  # fmt: skip
    # images are shared between the animals of one frame
    assert (
        c.get("/api/frame/1/cam0", headers=H).content
        == c.get("/api/frame/0/cam0", headers=H).content
    )
    kps = list(range(6))
    for i, animal in ((0, "animal0"), (1, "animal1")):
        body = {"version": 0, "labels": _labels_of(pair, _truth(pair, f0, animal), kps)}
        assert c.post(f"/api/instant/{i}", json=body, headers=H).status_code == 200
    st1 = c.get("/api/instant/1", headers=H).json()
    assert st1["animals"][0]["labeled"] and st1["animals"][1]["labeled"]
    # the other animal's labels, for reference
    other = st1["others"]["animal0"]["cam0"]
    t = pair[2]
    r0 = _truth(pair, f0, "animal0")
    k = next(k for k in kps if t.visible2d[r0, 0, k])
    np.testing.assert_allclose(other[t.keypoints[k]], t.points2d[r0, 0, k], atol=1e-3)
    ls = read_labels_h5(store.output)
    assert list(ls.frame_index) == [f0, f0] and list(ls.individual) == ["animal0", "animal1"]
    for r, animal in enumerate(("animal0", "animal1")):
        truth3d = t.points3d[_truth(pair, f0, animal), kps]
        err = np.linalg.norm(ls.points3d[r, kps] - truth3d, axis=-1)
        seen = ls.visible2d[r][:, kps].sum(0) >= 2
        assert seen.any() and np.nanmax(err[seen]) < 1.0  # mm: each animal on its own
    # the two animals are apart: one animal's triangulation is not the other's
    assert np.nanmin(np.linalg.norm(ls.points3d[0, kps] - ls.points3d[1, kps], axis=-1)) > 5.0


def test_resume_keeps_animals_and_refuses_mixing(pair, tmp_path: Path) -> None:
    out = tmp_path / "labels.h5"
    store = _store(pair, out, animals=("animal0", "animal1"))
    f0 = store.instants[0].frame
    labels = _labels_of(pair, _truth(pair, f0, "animal1"), [0, 1])
    _, pts, status = parse_body(
        json.dumps({"version": 0, "labels": labels}).encode(), store.session(1).rig,
        store.skeleton.keypoints,
    )  # fmt: skip
    store.save(1, 0, pts, status)
    again = _store(pair, out)  # no --animals: the file's animals
    # both animals, although only one has labels yet (the run records its animals)
    assert [x.individual for x in again.instants[:2]] == ["animal0", "animal1"]
    i1 = next(i for i, x in enumerate(again.instants) if x.key == (store.instants[1].key))
    np.testing.assert_allclose(again._points[i1], store._points[1])
    with pytest.raises(LabelStartError, match="holds labels of the animals"):
        _store(pair, out, animals=())
    # a one-animal file is not continued with several animals
    single = tmp_path / "single.h5"
    one = _store(pair, single, animals=())
    one.save(0, 0, pts, status)
    assert read_labels_h5(single).individual is None  # written as before
    with pytest.raises(LabelStartError, match="one animal per instant"):
        _store(pair, single, animals=("animal0", "animal1"))


def test_predictions_with_animal_axis_prefill_each_animal(pair, tmp_path: Path) -> None:
    folder, calib, t = pair
    frames = np.unique(t.frame_index)
    poses = np.stack(
        [np.stack([t.points3d[_truth(pair, f, a)] for a in ("animal0", "animal1")]) for f in frames]
    ).astype(np.float32)  # (T, A, K, 3)
    conf = np.full(poses.shape[:3], 0.9, np.float32)
    conf[:, 1] = 0.3
    pdir = tmp_path / "poses"
    path = pdir / "pair.poses.h5"
    write_poses_h5(PoseData(poses, conf, t.keypoints, frames, 25.0,
                            individuals=("animal0", "animal1")), path)  # fmt: skip
    with h5py.File(path, "a") as f:
        f.attrs["complete"] = True
    store = open_store([folder], calib, "rat", tmp_path / "l.h5", per_session=2, poses_dir=pdir)
    assert [x.individual for x in store.instants[:2]] == ["animal0", "animal1"]  # from them
    assert store.instants[0].confidence == pytest.approx(0.9)
    assert store.instants[1].confidence == pytest.approx(0.3)
    f0 = store.instants[0].frame
    for i, animal in ((0, "animal0"), (1, "animal1")):
        pred = store.state(i)["predicted"]["cam1"]
        r = _truth(pair, f0, animal)
        k = next(k for k in range(len(t.keypoints)) if t.visible2d[r, 1, k])
        np.testing.assert_allclose(pred[t.keypoints[k]], t.points2d[r, 1, k], atol=0.05)
