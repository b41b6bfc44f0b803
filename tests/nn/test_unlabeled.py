"""Training on unlabeled clips: the [unlabeled] table, the clips, the losses, a tiny run."""

from __future__ import annotations

import csv
import dataclasses

import cv2
import numpy as np
import pytest
import torch
from nn_toydata import TEMPLATE, toy_samples, write_toy_labels

from freipose.io.calibration_toml import write_calibration_toml
from freipose.io.labels import read_labels_h5
from freipose.nn.config import ConfigError, config_from_dict, config_to_dict
from freipose.nn.config_ranges import UNLABELED_RANGES
from freipose.nn.config_unlabeled import UnlabeledConfig
from freipose.nn.data import collate_prepared, prepare_sample
from freipose.nn.geometry import project_affine
from freipose.nn.model import build_model
from freipose.nn.train import train_from_config
from freipose.nn.unlabeled import UnlabeledDataError, clip_starts, open_unlabeled
from freipose.nn.unlabeled_losses import (
    RigidPairs,
    bone_loss,
    multiview_loss,
    rigid_pairs,
    temporal_loss,
    unlabeled_training,
)


def _config(unlabeled=None, **sched):
    tables = {
        "model": {"preset": "tiny", "cube_size": 300.0},
        "schedule": {"steps": 4, "checkpoint_every": 4, "eval_every": 4, **sched},
    }
    if unlabeled is not None:
        tables["unlabeled"] = unlabeled
    return config_from_dict(tables)


def test_unlabeled_table_read_checked_and_written():
    cfg = _config({"sessions": ["a", "b"], "share": 0.25, "weight_temporal": 2})
    assert cfg.unlabeled.enabled and cfg.unlabeled.weight_temporal == 2.0
    assert config_from_dict(config_to_dict(cfg)).unlabeled == cfg.unlabeled
    assert not _config().unlabeled.enabled
    with pytest.raises(ConfigError, match="unlabeled.share"):
        _config({"share": 2.0})
    with pytest.raises(ConfigError, match="unlabeled.centers"):
        _config({"centers": "detector"})
    with pytest.raises(ConfigError, match="one poses file per session"):
        _config({"sessions": ["a"], "centers": "poses"})
    with pytest.raises(ConfigError, match="unlabeled.wieght_bones.*weight_bones"):
        _config({"wieght_bones": 1.0})
    floats = {f.name for f in dataclasses.fields(UnlabeledConfig) if isinstance(f.default, float)}
    assert floats <= set(UNLABELED_RANGES)


def test_clips_per_step_follows_the_share():
    assert UnlabeledConfig(share=0.5, clip_frames=3).clips_per_step(6) == 2
    assert UnlabeledConfig(share=0.1, clip_frames=3).clips_per_step(2) == 1


def _out_batch(model, n=2):
    samples = toy_samples(n, seed=3)
    batch = collate_prepared([prepare_sample(s, model) for s in samples])
    P = torch.as_tensor(np.stack([s["points3d"] for s in samples]), dtype=torch.float32)
    uv, _ = project_affine(P, batch["K"], batch["R"], batch["t"], batch["dist"])
    out = {
        "P0": P.clone(),
        "P1": P.clone(),
        "points2d": uv.clone(),
        "confidence2d": torch.ones(uv.shape[:-1]),
    }
    return out, batch


def test_multiview_loss_counts_only_views_that_see_the_point():
    model = _config().model
    out, batch = _out_batch(model)
    assert float(multiview_loss(out, batch, model, 1.0)) < 1e-2
    out["points2d"][:, 1] += 8.0  # one view refined elsewhere
    off = float(multiview_loss(out, batch, model, 1.0))
    assert off > 0.3
    batch["view_mask"][:, 1] = False  # that view cannot see the animal
    assert float(multiview_loss(out, batch, model, 1.0)) < 1e-2
    batch["view_mask"][:, 1] = True
    out["confidence2d"][:, 1] = 0.0  # nor does it count without confidence
    assert float(multiview_loss(out, batch, model, 1.0)) < 1e-2


def test_temporal_loss_penalises_acceleration_not_steady_motion():
    model = _config().model
    t = torch.arange(4.0)[:, None, None]
    steady = (torch.as_tensor(TEMPLATE, dtype=torch.float32)[None] + 30.0 * t).reshape(4, 5, 3)
    assert float(temporal_loss(steady, 1, 4, model, 1.0)) < 1e-2
    jerk = steady.clone()
    jerk[2] += 80.0
    assert float(temporal_loss(jerk, 1, 4, model, 1.0)) > 0.5
    assert float(temporal_loss(jerk, 2, 2, model, 1.0)) == 0.0  # 2-frame clips: no acceleration


def test_rigid_pairs_and_bone_loss():
    rng = np.random.default_rng(0)
    pts = np.stack([TEMPLATE + rng.normal(0, 1.0, TEMPLATE.shape) for _ in range(20)])
    pts[:, 4] += rng.normal(0, 60.0, (20, 3))  # keypoint 4 moves freely
    bones = rigid_pairs(pts)
    assert len(bones.pairs) and not (bones.pairs == 4).any()
    assert np.bincount(bones.pairs.ravel(), minlength=5).max() <= 2
    model = _config().model
    poses = torch.as_tensor(TEMPLATE, dtype=torch.float32)[None]
    assert float(bone_loss(poses, bones, model, 1.0)) < 1e-3
    stretched = poses.clone()
    stretched[0, bones.pairs[0, 0]] += 50.0
    assert float(bone_loss(stretched, bones, model, 1.0)) > 0.1
    none = RigidPairs(np.zeros((0, 2), np.int64), np.zeros(0), np.zeros(0))
    assert float(bone_loss(stretched, none, model, 1.0)) == 0.0


def _write_session(folder, samples):
    """The samples' frames as one mp4 video per camera, with calibration.toml."""
    folder.mkdir(parents=True)
    rig = samples[0]["rig"]
    write_calibration_toml(rig, folder / "calibration.toml")
    for v, cam in enumerate(rig):
        path = str(folder / f"{cam.name}.mp4")
        w = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"mp4v"), 30, (cam.width, cam.height))
        for s in samples:
            w.write(s["images"][v])
        w.release()
    return folder


def _unlabeled_setup(tmp_path, extra=None):
    labels = write_toy_labels(tmp_path / "lab", toy_samples(4))
    _write_session(tmp_path / "day2", toy_samples(6, seed=5))
    unl = {"sessions": ["day2"], "clip_frames": 3, **(extra or {})}
    cfg_text = (
        '[data]\nlabels = "lab/labels.h5"\n[model]\npreset = "tiny"\ncube_size = 300.0\n'
        "[schedule]\nsteps = 3\ncheckpoint_every = 3\neval_every = 3\nlog_every = 1\n"
        "[unlabeled]\n" + "".join(f"{k} = {v!r}\n".replace("'", '"') for k, v in unl.items())
    )
    path = tmp_path / "train.toml"
    path.write_text(cfg_text)
    return path, labels


def test_clips_are_prepared_like_samples_and_repeat_by_step(tmp_path):
    path, labels_path = _unlabeled_setup(tmp_path)
    labels = read_labels_h5(labels_path)
    cfg = config_from_dict({**config_to_dict(_config()), "unlabeled": {"sessions": ["day2"]}})
    ut = unlabeled_training(cfg, tmp_path, labels)
    assert ut is not None
    ub = ut.clips.batch(7)
    n = ub.clips * ub.clip_frames + ub.clips
    assert ub.batch["images"].shape[:2] == (n, 3)
    assert "points3d" not in ub.batch
    # the equivariance copy sees a subset of the views (2 of 3)
    assert ub.batch["view_mask"][-ub.clips :].sum(1).tolist() == [2] * ub.clips
    again = ut.clips.batch(7).batch
    assert torch.equal(again["images"], ub.batch["images"])
    assert not torch.equal(ut.clips.batch(8).batch["images"], ub.batch["images"])
    ut.close()
    # every clip's instants need a centre
    sessions = open_unlabeled(cfg.unlabeled, tmp_path, labels)
    assert len(clip_starts(sessions, 3, 2)) == 6 - 4
    with pytest.raises(UnlabeledDataError, match="clip_frames"):
        clip_starts(sessions, 7, 1)


def test_training_with_unlabeled_clips_logs_their_terms(tmp_path):
    path, _ = _unlabeled_setup(tmp_path, {"weight_teacher": 0.5})
    model = train_from_config(path, tmp_path / "run", progress=False)
    assert model.name == "model.pt"
    with (tmp_path / "run" / "log.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 3
    for term in ("u_multiview", "u_p0p1", "u_temporal", "u_equivariance", "u_bones", "u_teacher"):
        assert all(np.isfinite(float(r[term])) for r in rows), term
    assert float(rows[-1]["u_multiview"]) > 0.0


def test_unlabeled_session_without_calibration_is_refused(tmp_path):
    path, _ = _unlabeled_setup(tmp_path)
    (tmp_path / "day2" / "calibration.toml").unlink()
    with pytest.raises(Exception, match="calibration"):
        train_from_config(path, tmp_path / "run", progress=False)
    assert not (tmp_path / "run" / "checkpoint.pt").exists()


def test_baseline_with_unlabeled_sessions_is_refused(tmp_path):
    path, _ = _unlabeled_setup(tmp_path)
    with pytest.raises(UnlabeledDataError, match="voxel network"):
        train_from_config(path, tmp_path / "run", progress=False, kind="baseline")


def test_refined_terms_wait_for_the_refinement_head(tmp_path):
    _, labels_path = _unlabeled_setup(tmp_path)
    cfg = config_from_dict(
        {**config_to_dict(_config(steps=10, refine_start=0.5)), "unlabeled": {"sessions": ["day2"]}}
    )
    ut = unlabeled_training(cfg, tmp_path, read_labels_h5(labels_path))
    assert ut is not None and ut.refine_from == 5
    net = build_model(cfg.model, 5)
    torch.manual_seed(0)
    for step, refined in ((4, False), (5, True)):
        total, parts = ut.loss(net, step, torch.device("cpu"), False)
        w = cfg.unlabeled
        rest = sum(getattr(w, "weight_" + k[2:]) * v for k, v in parts.items()
                   if k not in ("u_multiview", "u_p0p1"))  # fmt: skip
        both = w.weight_multiview * parts["u_multiview"] + w.weight_p0p1 * parts["u_p0p1"]
        expected = rest + (both if refined else 0.0)
        assert float(total.detach()) == pytest.approx(float(expected), rel=1e-4)
    ut.close()


def test_several_processes_are_refused_before_any_work(tmp_path, monkeypatch):
    path, _ = _unlabeled_setup(tmp_path)
    monkeypatch.setenv("WORLD_SIZE", "2")
    with pytest.raises(UnlabeledDataError, match="one process"):
        train_from_config(path, tmp_path / "run", progress=False)
    assert not (tmp_path / "run").exists()
