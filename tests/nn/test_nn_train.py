"""Training, resume, DDP, checkpoints, prediction and the train/eval commands (tiny preset)."""

from __future__ import annotations

import dataclasses
import json
import os
import socket

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from nn_toydata import toy_samples, toy_skeleton, write_toy_labels

from freipose.nn.checkpoint import CheckpointError, load_checkpoint, read_checkpoint
from freipose.nn.config import ConfigError, config_from_dict, load_config
from freipose.nn.evaluate import jpe, predict_dataset
from freipose.nn.inference import predict_batch
from freipose.nn.model import build_model
from freipose.nn.train import train_pose


def _cfg(**sched):
    return config_from_dict(
        {
            "model": {"preset": "tiny", "cube_size": 300.0},
            "schedule": {"steps": 8, "checkpoint_every": 4, "eval_every": 4, **sched},
        }
    )


def _weights(path):
    return read_checkpoint(path)["model"]


def _assert_same(a, b, atol):
    assert a.keys() == b.keys()
    for k in a:
        torch.testing.assert_close(a[k].float(), b[k].float(), atol=atol, rtol=0, msg=k)


def test_training_lowers_error(tmp_path):
    src = toy_samples(4)
    cfg = config_from_dict(
        {
            "model": {"preset": "tiny", "cube_size": 300.0},
            "schedule": {"steps": 40, "lr": 3e-3, "checkpoint_every": 40, "eval_every": 40},
            "augment": {"enabled": False},
        }
    )
    torch.manual_seed(cfg.schedule.seed)
    init = build_model(cfg.model, 5)
    before = np.nanmedian(jpe(*(lambda p: (p["P0"], p["gt"]))(predict_dataset(init, src))))
    path = train_pose(cfg, tmp_path, src, toy_skeleton(), src, progress=False)
    model, _, _ = load_checkpoint(path)
    after = np.nanmedian(jpe(*(lambda p: (p["P0"], p["gt"]))(predict_dataset(model, src))))
    assert after < 0.5 * before, (before, after)
    rows = (tmp_path / "log.csv").read_text().splitlines()
    assert rows[0].startswith("step,lr,loss") and len(rows) == 41
    assert (tmp_path / "log.png").stat().st_size > 0
    assert "[model]" in (tmp_path / "config.toml").read_text()


def test_resume_is_exact(tmp_path):
    src = toy_samples(5)
    cfg = _cfg()
    full = train_pose(cfg, tmp_path / "a", src, toy_skeleton(), progress=False)
    part = train_pose(cfg, tmp_path / "b", src, toy_skeleton(), progress=False, stop_after=4)
    assert part.name == "checkpoint.pt" and read_checkpoint(part)["step"] == 4
    with pytest.raises(ValueError, match="--resume"):
        train_pose(cfg, tmp_path / "b", src, toy_skeleton(), progress=False)
    resumed = train_pose(cfg, tmp_path / "b", src, toy_skeleton(), progress=False, resume=True)
    _assert_same(_weights(full), _weights(resumed), atol=1e-6)
    steps = [int(r.split(",")[0]) for r in (tmp_path / "b" / "log.csv").read_text().split()[1:]]
    assert steps == list(range(1, 9))


def _ddp_cfg():
    """The DDP comparison's run: 2 SGD steps of a global batch of 4, every head trained."""
    cfg = _cfg(batch_size=4, steps=2, refine_start=0.0)
    return dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, init="scratch"))


def _ddp_worker(rank, world, port, out):
    os.environ.update(
        MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(world)
    )
    torch.set_num_threads(1)
    torch.optim.Adam = torch.optim.SGD  # in this spawned process only (see the test)
    try:
        train_pose(_ddp_cfg(), out, toy_samples(4), toy_skeleton(), progress=False)
    finally:
        torch.distributed.destroy_process_group()


def _update_errors(start, a, b):
    """Per weight: |a's change - b's change| / |b's change| (norms over the tensor)."""
    out = {}
    for k in start:
        da, db = (x[k].double() - start[k].double() for x in (a, b))
        out[k] = float((da - db).norm() / db.norm()) if db.norm() > 0 else float(da.norm())
    return out


def _ddp_errors(tmp_path, monkeypatch):
    """The update errors of 2 gloo processes of 2 samples each against 1 process of 4."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    torch.multiprocessing.spawn(_ddp_worker, args=(2, port, str(tmp_path / "ddp")), nprocs=2)
    monkeypatch.setattr(torch.optim, "Adam", torch.optim.SGD)
    cfg = _ddp_cfg()
    single = train_pose(cfg, tmp_path / "one", toy_samples(4), toy_skeleton(), progress=False)
    torch.manual_seed(cfg.schedule.seed)
    start = build_model(cfg.model, 5).state_dict()
    return _update_errors(start, _weights(tmp_path / "ddp" / "model.pt"), _weights(single))


def test_ddp_gloo_matches_single_process(tmp_path, monkeypatch):
    """Two gloo processes of 2 samples each take the steps of one process with 4.

    Both train with SGD, whose update is the learning rate times the averaged gradient, so
    the weight changes of the two runs differ by the float32 rounding of the gradients
    (summed in another order and blocking, which depends on the CPU's vector width). A
    float32 sum of n terms is within n * eps of its exact value relative to the sum of the
    terms' magnitudes; the largest sums of the backward pass run over the crop pixels of
    every view of the batch. Adam is left out: it divides each gradient by its own
    magnitude and turns the rounding of a near-zero gradient into a change of up to the
    learning rate. Gradients summed instead of averaged, or a process whose batch is left
    out, change the update by a large fraction of itself.
    """
    errors = _ddp_errors(tmp_path, monkeypatch)
    cfg, views = _ddp_cfg(), 3
    terms = cfg.schedule.batch_size * views * cfg.model.crop_size**2
    tol = terms * float(torch.finfo(torch.float32).eps)
    worst = max(errors, key=errors.get)
    assert errors[worst] < tol, (worst, errors[worst], tol)


def test_checkpoint_hash_and_predict_batch(tmp_path):
    src = toy_samples(3)
    path = train_pose(_cfg(steps=2), tmp_path, src, toy_skeleton(), progress=False)
    model, config, skel = load_checkpoint(path)
    assert config.model.grid_size == 8 and skel.keypoints == toy_skeleton().keypoints
    centers = np.stack([s["points3d"].mean(0) for s in src])
    centers[1] = np.nan
    out = predict_batch(model, [s["images"] for s in src], [s["rig"] for s in src], centers)
    assert out["P1"].shape == (3, 5, 3) and out["points2d"].shape == (3, 3, 5, 2)
    assert np.isnan(out["P0"][1]).all() and np.isfinite(out["P0"][[0, 2]]).all()
    assert ((out["confidence"] >= 0) & (out["confidence"] <= 1)).all()
    # a single view works too (P1 then keeps P0's depth)
    one = predict_batch(model, [src[0]["images"][:1]], [src[0]["rig"].subset([0])], centers[:1])
    assert np.isfinite(one["P1"]).all()
    ck = torch.load(path, weights_only=False)
    k = next(iter(ck["model"]))
    ck["model"][k] = ck["model"][k] + 1
    torch.save(ck, tmp_path / "bad.pt")
    with pytest.raises(CheckpointError, match="hash"):
        read_checkpoint(tmp_path / "bad.pt")
    ck["model"][k] = ck["model"][k] - 1
    ck["version"] = 1  # one-level 2D heads: refused with a clear message
    torch.save(ck, tmp_path / "old.pt")
    with pytest.raises(CheckpointError, match="older FreiPose.*retrain"):
        read_checkpoint(tmp_path / "old.pt")
    (tmp_path / "trunc.pt").write_bytes(path.read_bytes()[:100])
    with pytest.raises(CheckpointError, match="truncated"):
        read_checkpoint(tmp_path / "trunc.pt")


def test_fusion_weights_per_keypoint_learn_faster_and_old_checkpoints_load(tmp_path):
    from dataclasses import replace

    from freipose.nn.checkpoint import serialize_checkpoint, state_hash
    from freipose.nn.model import FUSION_LR_SCALE, optimizer_groups

    src = toy_samples(3)
    cfg = _cfg(steps=4, refine_start=0.0, lr=1e-3)
    path = train_pose(cfg, tmp_path / "run", src, toy_skeleton(), progress=False)
    model, _, _ = load_checkpoint(path)
    w = model.prior_log_weight.detach()
    assert w.shape == (5,)  # one P0 weight per keypoint
    # 4 Adam steps move a parameter by at most ~4 lr; the fusion weights move further
    assert 4 * 1e-3 < float(w.abs().max()) <= 4 * 1e-3 * FUSION_LR_SCALE * 1.01
    groups = optimizer_groups(model)
    assert [g["lr_scale"] for g in groups] == [1.0, FUSION_LR_SCALE]
    assert sum(len(g["params"]) for g in groups) == len(list(model.parameters()))
    assert len(optimizer_groups(build_model(replace(cfg.model, kind="baseline"), 5))) == 1
    # a version 2 checkpoint with one weight for all keypoints still loads
    ck = torch.load(path, weights_only=False)
    ck["model"]["prior_log_weight"] = torch.tensor(0.5)
    ck["version"] = 2
    ck["weights_sha256"] = state_hash(ck["model"])
    (tmp_path / "v2.pt").write_bytes(serialize_checkpoint(ck))
    model, _, _ = load_checkpoint(tmp_path / "v2.pt")
    torch.testing.assert_close(model.prior_log_weight.detach(), torch.full((5,), 0.5))
    # ... but its optimizer state cannot be resumed
    ck = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)
    ck["optimizer"]["param_groups"] = ck["optimizer"]["param_groups"][:1]
    for g in ck["optimizer"]["param_groups"]:
        del g["lr_scale"]
    ck["step"] = 2
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "checkpoint.pt").write_bytes(serialize_checkpoint(ck))
    with pytest.raises(ValueError, match="older FreiPose.*cannot be resumed"):
        train_pose(cfg, tmp_path / "old", src, toy_skeleton(), progress=False, resume=True)


def test_config_validation(tmp_path):
    with pytest.raises(ConfigError, match="model.preset"):
        config_from_dict({"model": {"preset": "huge"}})
    with pytest.raises(ConfigError, match="unknown key schedule.stepz"):
        config_from_dict({"schedule": {"stepz": 3}})
    with pytest.raises(ConfigError, match="grid_size"):
        config_from_dict({"model": {"preset": "tiny", "grid_size": 9}})
    with pytest.raises(ConfigError, match=r"head_levels must be in 1..encoder_pools \(2\), got 3"):
        config_from_dict({"model": {"preset": "tiny", "head_levels": 3}})
    with pytest.raises(ConfigError, match=r"unproject_levels must be in 0..encoder_pools"):
        config_from_dict({"model": {"preset": "tiny", "unproject_levels": 3}})
    with pytest.raises(ConfigError, match=r"crop_fraction must be in \[0.1, 1\]"):
        config_from_dict({"model": {"preset": "tiny", "crop_fraction": 1.5}})
    p = tmp_path / "c.toml"
    p.write_text('[model]\npreset = "small"\ngrid_size = 16\n[schedule]\nlr = "fast"\n')
    with pytest.raises(ConfigError, match="schedule.lr must be a number"):
        load_config(p)
    p.write_text('[model]\npreset = "small"\ngrid_size = 16\n')
    cfg = load_config(p)
    assert cfg.model.grid_size == 16 and cfg.model.crop_size == 128


def test_train_and_eval_commands(tmp_path, monkeypatch):
    from freipose.cli.main import cli

    write_toy_labels(tmp_path / "train", toy_samples(4))
    write_toy_labels(tmp_path / "eval", toy_samples(3, seed=5))
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(
        '[data]\nlabels = "train/labels.h5"\neval_labels = "eval/labels.h5"\n'
        '[model]\npreset = "tiny"\n[schedule]\nsteps = 2\n'
    )
    runner = CliRunner()
    r = runner.invoke(cli, ["-q", "train", str(cfg), "--out", str(tmp_path / "run")])
    assert r.exit_code == 0, r.output
    r = runner.invoke(
        cli, ["-q", "train", str(cfg), "--stage", "baseline", "--out", str(tmp_path / "base")]
    )
    assert r.exit_code == 0, r.output
    r = runner.invoke(
        cli,
        [
            "-q",
            "eval",
            str(tmp_path / "run" / "model.pt"),
            str(tmp_path / "eval" / "labels.h5"),
            "-o",
            str(tmp_path / "ev"),
            "--baseline",
            str(tmp_path / "base" / "model.pt"),
        ],
    )
    assert r.exit_code == 0, r.output
    assert "voxel_P1: median JPE" in r.output and "baseline: median JPE" in r.output
    m = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert set(m) == {"voxel_P0", "voxel_P1", "baseline", "references", "comparisons"}
    assert m["voxel_P0"]["overall"]["n"] == 15
    pairs = [(c["a"], c["b"]) for c in m["comparisons"]]
    assert ("voxel_P1", "baseline") in pairs and ("voxel_P0", "voxel_P1") not in pairs
    assert "voxel_P1 vs baseline: " in r.output
    for f in ("pck.csv", "pck.png", "jpe_boxplot.png", "jpe_per_keypoint.csv"):
        assert (tmp_path / "ev" / f).stat().st_size > 0
    # --fusion-reject overrides the checkpoint's setting for this evaluation: P0 is the same
    ev_args = [
        "-q",
        "eval",
        str(tmp_path / "run" / "model.pt"),
        str(tmp_path / "eval" / "labels.h5"),
    ]
    r = runner.invoke(cli, [*ev_args, "-o", str(tmp_path / "ev0"), "--fusion-reject", "0"])
    assert r.exit_code == 0, r.output
    m0 = json.loads((tmp_path / "ev0" / "metrics.json").read_text())
    assert m0["voxel_P0"]["overall"] == m["voxel_P0"]["overall"]
    r = runner.invoke(cli, [*ev_args, "-o", str(tmp_path / "ev1"), "--fusion-reject", "-1"])
    assert r.exit_code != 0 and "fusion_reject must be in [0, 1000]" in r.output
    # another --map-window than the one chosen on the validation labels (0: the whole maps):
    # the refinement's points (P1) change, P0 does not
    used = m["voxel_P1"]["inference_settings"]["used"]["map_window"]
    other = 0 if used else 3
    r = runner.invoke(cli, [*ev_args, "-o", str(tmp_path / "ev2"), "--map-window", str(other)])
    assert r.exit_code == 0, r.output
    m2 = json.loads((tmp_path / "ev2" / "metrics.json").read_text())
    assert m2["voxel_P0"]["overall"] == m["voxel_P0"]["overall"]
    assert m2["voxel_P1"]["overall"] != m["voxel_P1"]["overall"]
    # smooth --validation measures the held-out error with the settings the poses record
    # (its predictions, before the per-keypoint RMS that needs more than these 3 instants)
    from freipose.nn.config import InferenceOverrides
    from freipose.predict import smooth_error

    monkeypatch.setattr(smooth_error, "validation_error", lambda pred, *_: pred)
    ckpt, held_out = tmp_path / "run" / "model.pt", tmp_path / "eval" / "labels.h5"
    own = smooth_error.model_validation_error(ckpt, held_out)
    whole = smooth_error.model_validation_error(
        ckpt, held_out, overrides=InferenceOverrides(map_window=other)
    )
    assert own.shape == whole.shape == (3, 5, 3) and not np.allclose(own, whole)
    r = runner.invoke(cli, [*ev_args, "-o", str(tmp_path / "ev3"), "--map-window", "-1"])
    assert r.exit_code != 0 and "map_window must be >= 0" in r.output
    # errors are user errors, not tracebacks
    r = runner.invoke(cli, ["train", str(cfg), "--out", str(tmp_path / "run")])
    assert r.exit_code != 0 and "--resume" in r.output
    bad = tmp_path / "bad.toml"
    bad.write_text('[model]\npreset = "nope"\n')
    r = runner.invoke(cli, ["train", str(bad)])
    assert r.exit_code != 0 and "model.preset" in r.output


def test_detector_stage_without_detector_module(tmp_path, monkeypatch):
    import sys

    from freipose.cli.main import cli

    monkeypatch.setitem(sys.modules, "freipose.detect.train", None)  # import fails
    cfg = tmp_path / "cfg.toml"
    cfg.write_text('[model]\npreset = "tiny"\n')
    r = CliRunner().invoke(cli, ["train", str(cfg), "--stage", "detector"])
    assert r.exit_code != 0 and "detector training is not available" in r.output


@pytest.mark.gpu
def test_tiny_training_on_gpu_with_autocast(tmp_path):
    src = toy_samples(4)
    cfg = _cfg(steps=4, amp=True)
    path = train_pose(cfg, tmp_path, src, toy_skeleton(), src, device="cuda", progress=False)
    model, _, _ = load_checkpoint(path, "cuda")
    pred = predict_dataset(model, src)
    assert np.isfinite(pred["P1"]).all()


def test_a_shorter_run_drops_the_learning_rate_at_the_presets_share_of_its_steps():
    def sched(preset: str, **table):
        return config_from_dict({"model": {"preset": preset}, "schedule": table}).schedule

    assert sched("small").lr_decay_steps == 2000  # the preset's own: 2000 of 3000
    short = sched("small", steps=600)
    assert short.lr_decay_steps == 400 and short.lr_at(399) == 1e-3
    assert short.lr_at(400) == pytest.approx(1e-4)
    assert sched("paper", steps=1000).lr_decay_steps == 500  # 30000 of 60000
    assert sched("small", steps=600, lr_decay_steps=100).lr_decay_steps == 100  # given: kept
