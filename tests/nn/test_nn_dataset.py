"""MultiViewDataset: frames, cameras and labels per time instant, across different rigs."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest
import torch.utils.data

from freipose.io.labels import LabelSet, SessionInfo, write_labels_h5
from freipose.io.video import VideoWriter
from freipose.nn.dataset import LabelsDataError, MultiViewDataset, list_collate
from freipose.testing import make_circle_rig

W, H = 64, 48


def _video(path: Path, n: int, cam: int) -> None:
    with VideoWriter(path, 10, (W, H)) as w:
        for i in range(n):
            img = np.zeros((H, W, 3), np.uint8)
            img[..., 0] = 10 * i  # frame index in blue
            img[..., 2] = 40 * cam  # camera in red
            w.write(img)


def _labels(tmp_path: Path, rng: np.random.Generator, frames: int = 6) -> Path:
    rig_a = make_circle_rig(3, size=(W, H), focal=60)
    rig_b = make_circle_rig(2, size=(W, H), focal=60).subset(["cam0", "cam1"])
    cams = ("cam0", "cam1", "cam2")
    vids_a, vids_b = {}, {}
    for c in range(3):
        _video(tmp_path / "a" / f"cam{c}.mkv", frames, c)
        vids_a[f"cam{c}"] = f"a/cam{c}.mkv"
    for c in range(2):
        _video(tmp_path / "b" / f"cam{c}.mkv", frames, c)
        vids_b[f"cam{c}"] = f"b/cam{c}.mkv"
    n, k = 5, 4
    p3 = rng.normal(0, 50, (n, k, 3))
    p2 = np.full((n, 3, k, 2), np.nan)
    sess = np.array(["a", "a", "a", "b", "b"], dtype=object)
    for i in range(n):
        rig = rig_a if sess[i] == "a" else rig_b
        uv = rig.project(p3[i])
        p2[i, : len(rig)] = uv
    p2[0, 1, 2] = np.nan
    p3[1, 3] = np.nan
    labels = LabelSet(
        sess,
        np.array([0, 2, 5, 1, 3]),
        p2,
        p3,
        cams,
        ("k0", "k1", "k2", "k3"),
        {"a": SessionInfo(rig_a, vids_a, 10.0), "b": SessionInfo(rig_b, vids_b, 10.0)},
    )
    write_labels_h5(labels, tmp_path / "labels.h5")
    return tmp_path / "labels.h5"


def test_samples_frames_and_labels(tmp_path, rng):
    path = _labels(tmp_path, rng)
    ds = MultiViewDataset(path, cache_size=4)
    assert len(ds) == 5
    s = ds[2]
    assert s["session"] == "a" and s["frame_index"] == 5 and s["index"] == 2
    assert list(s["rig"].names) == ["cam0", "cam1", "cam2"]
    assert len(s["images"]) == 3
    for c, img in enumerate(s["images"]):
        assert img.shape == (H, W, 3) and img.dtype == np.uint8
        assert abs(float(img[..., 0].mean()) - 50) < 3  # frame 5
        assert abs(float(img[..., 2].mean()) - 40 * c) < 3
    # a session with a different rig: two views
    s = ds[4]
    assert s["session"] == "b" and len(s["images"]) == 2 and s["points2d"].shape == (2, 4, 2)
    assert list(s["rig"].names) == ["cam0", "cam1"]
    assert abs(float(s["images"][0][..., 0].mean()) - 30) < 3
    # masks
    s = ds[0]
    assert not s["visible2d"][1, 2] and s["visible2d"].sum() == 3 * 4 - 1
    np.testing.assert_array_equal(s["mask3d"], [True] * 4)
    assert ds[1]["mask3d"].tolist() == [True, True, True, False]
    np.testing.assert_allclose(s["points2d"], ds.labels.points2d[0])


def test_camera_subset_no_images_and_loader(tmp_path, rng):
    path = _labels(tmp_path, rng)
    ds = MultiViewDataset(path, cameras=["cam2", "cam0"], load_images=False)
    s = ds[0]
    assert s["images"] == [] and list(s["rig"].names) == ["cam0", "cam2"]
    np.testing.assert_allclose(s["points2d"], ds.labels.points2d[0, [0, 2]])
    assert list(ds[3]["rig"].names) == ["cam0"]
    with pytest.raises(LabelsDataError, match="not in the labels"):
        MultiViewDataset(path, cameras=["nope"])
    # workers: the dataset pickles without open videos and reopens them in the worker
    full = MultiViewDataset(path)
    full[0]
    clone = pickle.loads(pickle.dumps(full))
    assert len(clone[1]["images"]) == 3
    loader = torch.utils.data.DataLoader(full, batch_size=2, collate_fn=list_collate)
    batches = list(loader)
    assert [len(b) for b in batches] == [2, 2, 1]
    assert [len(x["images"]) for b in batches for x in b] == [3, 3, 3, 2, 2]
    # a worker process: samples (with their CameraRig) travel back pickled
    loader = torch.utils.data.DataLoader(full, batch_size=5, collate_fn=list_collate, num_workers=1)
    (batch,) = list(loader)
    assert [list(x["rig"].names) for x in batch][3] == ["cam0", "cam1"]
    np.testing.assert_array_equal(batch[4]["images"][1], full[4]["images"][1])


def test_errors_missing_video_and_frame_past_end(tmp_path, rng):
    path = _labels(tmp_path, rng, frames=4)  # frame 5 of session a is past the end
    ds = MultiViewDataset(path)
    with pytest.raises(LabelsDataError, match=r"cam0\.mkv.*frame 5.*4 frames"):
        ds[2]
    with pytest.raises(LabelsDataError, match="frame 5"):
        ds.validate()
    (tmp_path / "b" / "cam1.mkv").unlink()
    ds = MultiViewDataset(path)
    with pytest.raises(LabelsDataError, match=r"camera 'cam1'.*cam1\.mkv"):
        ds[3]
    with pytest.raises(IndexError):
        ds[5]


def test_full_cache_reads_each_video_ahead_in_one_pass(tmp_path, rng):
    from freipose.io.video import FrameSource

    path = _labels(tmp_path, rng)  # session a: frames 0, 2 and 5 labeled
    ds = MultiViewDataset(path)
    first = ds[2]  # frame 5 of session a
    src = ds._sources[("a", "cam1")]
    assert sorted(src._cache) == [0, 2, 5]  # every labeled frame, decoded in order
    plain = FrameSource(tmp_path / "a" / "cam1.mkv")
    np.testing.assert_array_equal(first["images"][1], plain.read(5))
    np.testing.assert_array_equal(ds[0]["images"][1], plain.read(0))
    assert ("b", "cam0") not in ds._sources  # a video is read when first used
    fixed = MultiViewDataset(path, cache_size=8)  # a cache size given: no read-ahead
    fixed[2]
    assert 2 not in fixed._sources[("a", "cam1")]._cache


def test_cache_budget_is_at_most_an_eighth_of_the_memory(monkeypatch):
    import freipose.nn.dataset as dataset

    pages = {"SC_PAGE_SIZE": 4096, "SC_PHYS_PAGES": 2**20}  # a 4 GiB machine
    monkeypatch.setattr(dataset.os, "sysconf", lambda name: pages[name])
    assert dataset.cache_budget() == 2**29  # 512 MiB, below CACHE_BYTES
    pages["SC_PHYS_PAGES"] = 2**24  # 64 GiB
    assert dataset.cache_budget() == dataset.CACHE_BYTES

    def unknown(name):
        raise ValueError(name)

    monkeypatch.setattr(dataset.os, "sysconf", unknown)
    assert dataset.cache_budget() == dataset.CACHE_BYTES


def test_default_cache_keeps_every_labeled_frame_when_they_fit(tmp_path, rng, monkeypatch):
    import freipose.nn.dataset as dataset

    path = _labels(tmp_path, rng)  # 3 labeled frames of session a, 2 of b
    monkeypatch.setattr(dataset, "CACHE_FRAMES", 2)
    assert MultiViewDataset(path).cache_size == 3  # the most labeled frames of one video
    # 3 videos x 3 frames + 2 x 2 frames of 64 x 48 x 3 bytes: over a smaller budget, the
    # fixed count
    monkeypatch.setattr(dataset, "CACHE_BYTES", 13 * W * H * 3 - 1)
    assert MultiViewDataset(path).cache_size == 2
    monkeypatch.setattr(dataset, "CACHE_BYTES", 13 * W * H * 3)
    ds = MultiViewDataset(path)
    assert ds.cache_size == 3
    first = ds[2]["images"][0]
    again = ds[2]["images"][0]
    assert again is first  # from the cache, shared: so read-only
    with pytest.raises(ValueError, match="read-only"):
        first[0, 0, 0] = 1
