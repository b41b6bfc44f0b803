"""Starting weights of a training run: model.init = base | scratch | a checkpoint path."""

from __future__ import annotations

import json
import logging
from dataclasses import replace

import pytest
import torch
from click.testing import CliRunner
from nn_toydata import toy_samples, toy_skeleton

import freipose.models as models
from freipose.nn.checkpoint import read_checkpoint
from freipose.nn.config import ConfigError, config_from_dict
from freipose.nn.init import ARCH_KEYS, InitError, architecture, initialize, keypoint_tensors
from freipose.nn.model import build_model
from freipose.nn.train import train_pose
from freipose.skeleton import Skeleton


def _cfg(init: str = "scratch", **model):
    return config_from_dict(
        {
            "model": {"preset": "tiny", "cube_size": 300.0, "init": init, **model},
            "schedule": {"steps": 2, "checkpoint_every": 2, "eval_every": 2},
        }
    )


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny voxel network trained 2 steps on the 5-keypoint toy skeleton (model.pt)."""
    out = tmp_path_factory.mktemp("base_run")
    return train_pose(_cfg(), out, toy_samples(2), toy_skeleton(), progress=False)


@pytest.fixture
def shipped(tmp_path, monkeypatch, trained):
    """A package-data folder that ships ``trained`` as the tiny voxel base."""
    (tmp_path / "voxel_tiny.pt").write_bytes(trained.read_bytes())
    entry = {
        "name": "voxel",
        "kind": "voxel",
        "file": "voxel_tiny.pt",
        "architecture": architecture(_cfg().model),
        "steps": 2,
    }
    (tmp_path / "bases.json").write_text(json.dumps({"bases": [entry]}))
    monkeypatch.setattr(models, "_root", lambda: tmp_path)
    return read_checkpoint(trained)["model"]


def _fresh(cfg, k):
    torch.manual_seed(0)
    return build_model(cfg.model, k)


def test_base_gives_every_weight_of_the_shipped_model(shipped, caplog):
    cfg = _cfg("base")
    model = _fresh(cfg, 5)
    with caplog.at_level(logging.INFO, logger="freipose.nn.init"):
        res = initialize(model, cfg.model, toy_skeleton())
    assert res.source == "base:voxel" and res.fresh == ()
    for name, v in model.state_dict().items():
        torch.testing.assert_close(v, shipped[name], msg=name)
    assert "starting from the base model 'voxel'" in caplog.text


def test_another_skeleton_keeps_all_but_the_keypoint_layers(shipped, caplog):
    cfg = _cfg("base")
    other = Skeleton(name="paw", keypoints=("a", "b", "c"))
    model = _fresh(cfg, 3)
    untouched = _fresh(cfg, 3).state_dict()
    with caplog.at_level(logging.INFO, logger="freipose.nn.init"):
        res = initialize(model, cfg.model, other)
    per_kp = keypoint_tensors(cfg.model, 3)
    assert set(res.fresh) == per_kp and "prior_log_weight" in per_kp
    assert any(n.startswith("unet.") for n in per_kp)  # the 3D output layers
    for name, v in model.state_dict().items():
        want = untouched[name] if name in per_kp else shipped[name]
        torch.testing.assert_close(v, want, msg=name)
    assert "another skeleton" in caplog.text and "start fresh" in caplog.text
    # the same number of keypoints with other names is another skeleton too
    renamed = Skeleton(name="x", keypoints=tuple(f"n{i}" for i in range(5)))
    assert set(initialize(_fresh(cfg, 5), cfg.model, renamed).fresh) == keypoint_tensors(
        cfg.model, 5
    )


def test_no_base_for_the_architecture_warns_and_starts_from_scratch(shipped, caplog):
    cfg = _cfg("base", feature_channels=16)  # another layer width: no base fits
    model = _fresh(cfg, 5)
    with caplog.at_level(logging.WARNING, logger="freipose.nn.init"):
        assert initialize(model, cfg.model, toy_skeleton()).source == "scratch"
    for name, v in model.state_dict().items():
        torch.testing.assert_close(v, _fresh(cfg, 5).state_dict()[name])
    assert "no base model is shipped" in caplog.text and 'model.init = "scratch"' in caplog.text
    # settings that do not change the weights' shapes (cube, grid, crop) still take the base
    near = _cfg("base", cube_size=250.0, grid_size=16)
    assert initialize(_fresh(near, 5), near.model, toy_skeleton()).source == "base:voxel"


def test_init_from_a_checkpoint_path_and_its_checks(trained, tmp_path):
    cfg = _cfg(str(trained))
    model = _fresh(cfg, 5)
    assert initialize(model, cfg.model, toy_skeleton()).loaded == len(model.state_dict())
    torch.testing.assert_close(model.state_dict(), read_checkpoint(trained)["model"])
    with pytest.raises(InitError, match="feature_channels 8 there, 16 here"):
        wide = _cfg(str(trained), feature_channels=16)
        initialize(_fresh(wide, 5), wide.model, toy_skeleton())
    with pytest.raises(InitError, match="kind 'voxel' there, 'baseline' here"):
        base = _cfg(str(trained), kind="baseline")
        initialize(_fresh(base, 5), base.model, toy_skeleton())
    with pytest.raises(ConfigError, match="set only one of them"):
        _cfg(str(trained), pretrained=str(trained))
    assert set(ARCH_KEYS) <= set(architecture(cfg.model))


def test_training_starts_from_the_init_and_resume_ignores_it(trained, tmp_path):
    src = toy_samples(2)
    cfg = _cfg(str(trained))
    cfg = replace(cfg, schedule=replace(cfg.schedule, lr=1e-9, steps=2))
    out = train_pose(cfg, tmp_path / "a", src, toy_skeleton(), progress=False, stop_after=1)
    start = read_checkpoint(trained)["model"]
    got = read_checkpoint(out)["model"]
    for name in start:
        torch.testing.assert_close(got[name].float(), start[name].float(), atol=1e-5, rtol=0)
    # a checkpoint written before model.init existed resumes (init only picks the start)
    ckpt = torch.load(out, weights_only=False)
    del ckpt["config"]["model"]["init"]
    torch.save(ckpt, out)
    final = train_pose(cfg, tmp_path / "a", src, toy_skeleton(), progress=False, resume=True)
    assert read_checkpoint(final)["step"] == 2


def test_train_command_init_option_and_relative_init_path(trained, tmp_path):
    from nn_toydata import write_toy_labels

    from freipose.cli.main import cli

    write_toy_labels(tmp_path / "train", toy_samples(2))
    (tmp_path / "start.pt").write_bytes(trained.read_bytes())
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(
        '[data]\nlabels = "train/labels.h5"\n[model]\npreset = "tiny"\ncube_size = 300.0\n'
        'init = "start.pt"\n[schedule]\nsteps = 1\nlr = 1e-9\n'
    )
    start = read_checkpoint(trained)["model"]
    runs = {"config": [], "option": ["--init", str(trained)], "scratch": ["--init", "scratch"]}
    for name, extra in runs.items():
        r = CliRunner().invoke(
            cli, ["-q", "train", str(cfg), "--out", str(tmp_path / name), *extra]
        )
        assert r.exit_code == 0, r.output
        got = read_checkpoint(tmp_path / name / "model.pt")["model"]
        close = all(torch.allclose(got[k].float(), start[k].float(), atol=1e-5) for k in start)
        assert close == (name != "scratch"), name


def test_the_shipped_bases_fit_the_small_preset_and_the_demo_detector():
    from freipose.detect.init import initialize_detector
    from freipose.detect.model import DetectorConfig, DetectorNet
    from freipose.skeleton import load_skeleton

    bases = {b.name: b for b in models.shipped_bases()}  # the installed package data
    assert set(bases) == {"voxel", "baseline", "detector"}
    for kind in ("voxel", "baseline"):
        cfg = config_from_dict({"model": {"preset": "small", "kind": kind}})
        res = initialize(build_model(cfg.model, 12), cfg.model, load_skeleton("rat"))
        assert res.source == f"base:{kind}" and res.fresh == () and res.loaded > 0
        assert bases[kind].entry["data"]["train_seeds"][0] >= 10_000  # disjoint seeds
    det = DetectorNet(DetectorConfig(input_size=128, width=0.35, neck_channels=24))
    assert initialize_detector(det, "base") == "base:detector"
    assert sum(b.entry["size_bytes"] for b in bases.values()) < 5_000_000


def test_a_warm_started_base_counts_the_steps_it_started_from(tmp_path, monkeypatch):
    entry = {"name": "voxel", "kind": "voxel", "file": "v.pt", "architecture": {}, "steps": 8000}
    entry["started_from"] = {"steps": 5000, "command": "python benchmarks/train_base.py"}
    (tmp_path / "v.pt").write_bytes(b"")
    (tmp_path / "bases.json").write_text(json.dumps({"bases": [entry]}))
    monkeypatch.setattr(models, "_root", lambda: tmp_path)
    (base,) = models.shipped_bases()
    assert base.steps == 13000 and models.total_steps({"steps": 7}) == 7
