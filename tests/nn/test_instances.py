"""The other animals painted out of an animal's views (``model.mask_others``).

On a rendered two-rat session: the painting covers the other animal and never this one's
body, leaves the input frames untouched, goes through ``prepare_sample`` only with the
option and other animals in the sample, and the evaluation's painted passes use the
network's own earlier poses, never the other animals' labels.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from freipose.io.labels import read_labels_h5
from freipose.nn.config import ModelConfig
from freipose.nn.data import prepare_sample
from freipose.nn.dataset import MultiViewDataset
from freipose.nn.instances import PAINT_VALUE, body_masks, paint_other_animals
from freipose.synth import SceneConfig, generate_session

BASE = Path(__file__).parents[2] / "freipose" / "models" / "voxel_small.pt"


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> MultiViewDataset:
    """Two rats, three 320x256 cameras, 4 frames (rows: one per animal and frame)."""
    out = tmp_path_factory.mktemp("instances") / "pair"
    cfg = SceneConfig(n_cameras=3, frames=4, size=(320, 256), seed=3, animals=2,
                      motion_blur=False)  # fmt: skip
    paths = generate_session(out, cfg, workers=1, progress=False)
    return MultiViewDataset(paths.labels)


def test_others_painted_never_own_body(pair: MultiViewDataset) -> None:
    s = pair[0]
    assert s["others3d"].shape == (1,) + s["points3d"].shape  # the other rat's labels
    rig = s["rig"]
    before = [im.copy() for im in s["images"]]
    out = paint_other_animals(s["images"], rig, s["points3d"], s["others3d"], 20.0)
    for im, b in zip(s["images"], before, strict=True):
        assert np.array_equal(im, b)  # the input frames are not modified
    sizes = [(im.shape[1], im.shape[0]) for im in before]
    own = body_masks(rig, s["points3d"][None], 20.0, sizes)[0]
    theirs = body_masks(rig, s["others3d"], 20.0, sizes)[0]
    painted_any = False
    for v, (im, b) in enumerate(zip(out, before, strict=True)):
        changed = (im != b).any(-1)
        assert not (changed & own[v]).any()  # nothing of this rat's body is touched
        assert not (changed & ~theirs[v]).any()  # only the other rat's body is
        assert (im[changed] == PAINT_VALUE).all()
        # the other rat's visible keypoints away from this rat are painted
        uv = rig.project(s["others3d"][0])[v]
        for x, y in np.round(uv).astype(int):
            if 0 <= x < sizes[v][0] and 0 <= y < sizes[v][1] and not own[v][y, x]:
                assert (im[y, x] == PAINT_VALUE).all()
                painted_any = True
    assert painted_any


def test_nothing_to_paint() -> None:
    from freipose.synth import default_rig

    rig = default_rig(2, (64, 48))
    ims = [np.zeros((48, 64, 3), np.uint8) for _ in range(2)]
    out = paint_other_animals(ims, rig, None, np.full((1, 5, 3), np.nan), 20.0)
    assert all(a is b for a, b in zip(out, ims, strict=True))


def test_prepare_sample_paints_only_with_the_option(pair: MultiViewDataset) -> None:
    s = pair[0]
    plain = ModelConfig(crop_size=64, grid_size=16, cube_size=320.0)
    masked = dataclasses.replace(plain, mask_others=True)
    ref = prepare_sample(s, plain)["images"]
    got = prepare_sample(s, masked)["images"]
    assert not np.array_equal(ref, got)  # the other rat is in this rat's crops
    without = {k: v for k, v in s.items() if k != "others3d"}
    np.testing.assert_array_equal(prepare_sample(without, masked)["images"], ref)  # type: ignore[arg-type]


def test_evaluation_paints_at_its_own_poses(pair: MultiViewDataset, monkeypatch) -> None:
    """Painted passes see the previous pass's P1 as the poses, not the labels."""
    if not BASE.is_file():
        pytest.skip(f"the shipped base model {BASE} is not in this checkout")
    import freipose.nn.data as data_mod
    import freipose.nn.evaluate as ev
    from freipose.nn.checkpoint import load_checkpoint

    model, _, _ = load_checkpoint(BASE)
    model.cfg = dataclasses.replace(model.cfg, mask_others=True, mask_passes=2)
    seen: list[tuple[np.ndarray | None, np.ndarray | None]] = []
    orig = data_mod._other_animals_painted

    def spy(sample, rig, images, model_cfg, aug):
        seen.append((sample.get("own3d"), sample.get("others3d")))
        return orig(sample, rig, images, model_cfg, aug)

    monkeypatch.setattr(data_mod, "_other_animals_painted", spy)
    out = ev.predict_dataset(model, pair, batch_size=4)
    n = len(out["index"])
    assert n == len(pair) and len(seen) == 3 * n  # a first pass and two painted passes
    labels = read_labels_h5(pair.labels) if isinstance(pair.labels, Path) else pair.labels
    first = seen[:n]
    assert all(o is None for o, _ in first)  # the first pass: no poses, nothing painted
    painted = seen[n:]
    for own, others in painted:
        assert own is not None and others is not None and others.shape[0] == 1
        # predictions, not the labels (the network is a few mm off everywhere)
        assert not any(np.allclose(own, p, equal_nan=True) for p in labels.points3d)
    assert np.isfinite(out["P1"]).all()


def test_training_warns_when_labels_hold_one_animal(tmp_path, monkeypatch, caplog) -> None:
    """model.mask_others with one animal per instant: nothing to paint, and the run says so."""
    import logging

    import freipose.nn.train as train_mod
    from freipose.synth import generate_session as gen

    paths = gen(tmp_path / "one", SceneConfig(n_cameras=2, frames=2, size=(160, 128), seed=1),
                workers=1, progress=False)  # fmt: skip
    cfg = tmp_path / "train.toml"
    cfg.write_text(f'[data]\nlabels = "{paths.labels}"\n\n[model]\npreset = "tiny"\n'
                   "mask_others = true\n", encoding="utf-8")  # fmt: skip
    monkeypatch.setattr(train_mod, "train_pose", lambda *a, **k: tmp_path / "model.pt")
    with caplog.at_level(logging.WARNING, logger="freipose.nn.instances"):
        train_mod.train_from_config(cfg, tmp_path / "run", progress=False)
    assert "nothing is painted" in caplog.text and "--animals" in caplog.text


def test_predict_batch_paints_the_given_animals(pair: MultiViewDataset) -> None:
    """The inference entry (predict --animals): poses of the other animals change the input
    only with model.mask_others, and unknown (NaN) poses paint nothing."""
    if not BASE.is_file():
        pytest.skip(f"the shipped base model {BASE} is not in this checkout")
    from freipose.nn.checkpoint import load_checkpoint
    from freipose.nn.inference import predict_batch

    model, _, _ = load_checkpoint(BASE)
    s = pair[0]
    frames, rigs = [s["images"]], [s["rig"]]
    centre = np.nanmean(s["points3d"], axis=0)[None]
    own, others = s["points3d"][None], s["others3d"][None]
    nan = (own, np.full_like(others, np.nan))
    plain = predict_batch(model, frames, rigs, centre)["P1"]
    np.testing.assert_array_equal(predict_batch(model, frames, rigs, centre, (own, others))["P1"],
                                  plain)  # fmt: skip
    model.cfg = dataclasses.replace(model.cfg, mask_others=True)
    np.testing.assert_array_equal(predict_batch(model, frames, rigs, centre, nan)["P1"], plain)
    painted = predict_batch(model, frames, rigs, centre, (own, others))["P1"]
    assert np.isfinite(painted).all() and not np.array_equal(painted, plain)
