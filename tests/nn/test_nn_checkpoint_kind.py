"""Checkpoint kinds: every FreiPose checkpoint is recognised by its header, read without
running code from it, and a file of the wrong kind is refused with a message that names
the option and the command that writes the right kind (never PyTorch's unsafe-load advice)."""

from __future__ import annotations

import random

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from nn_toydata import toy_skeleton

from freipose.cli.main import cli
from freipose.detect.detector import (
    Detector,
    DetectorCheckpointError,
    load_backbone_weights,
    save_checkpoint,
)
from freipose.detect.model import DetectorConfig, DetectorNet
from freipose.io.checkpoints import CheckpointFileError, checkpoint_kind
from freipose.nn.checkpoint import (
    CheckpointError,
    load_checkpoint,
    read_checkpoint,
    serialize_checkpoint,
    training_checkpoint,
)
from freipose.nn.config import config_from_dict
from freipose.nn.model import build_model, optimizer_groups

TINY_DET = DetectorConfig(input_size=64, width=0.25, neck_channels=8)
POSE_AS_DETECTOR = (
    "{} is a pose-network checkpoint; --detector takes a detector checkpoint "
    "(`freipose train CONFIG --stage detector`)"
)
DETECTOR_AS_MODEL = (
    "{} is a detector checkpoint; --model takes a pose-network checkpoint (`freipose train CONFIG`)"
)
OTHER = "{} is not a FreiPose checkpoint (or written by another program); "


def _pose(path, kind="voxel"):
    """A pose checkpoint as ``freipose train`` writes it (untrained weights)."""
    cfg = config_from_dict({"model": {"preset": "tiny", "kind": kind}})
    torch.manual_seed(0)
    model = build_model(cfg.model, len(toy_skeleton().keypoints))
    opt = torch.optim.Adam(optimizer_groups(model))
    rng = {
        "torch": torch.get_rng_state(),
        "numpy": np.random.get_state(),
        "python": random.getstate(),
    }
    ckpt = training_checkpoint(model, cfg, toy_skeleton(), opt, rng, 3, False)
    path.write_bytes(serialize_checkpoint(ckpt))
    return path


def _detector(path, **extra):
    torch.manual_seed(0)
    save_checkpoint(path, DetectorNet(TINY_DET), extra=extra)
    return path


@pytest.fixture
def files(tmp_path):
    junk = tmp_path / "junk.pt"
    junk.write_bytes(np.random.default_rng(0).bytes(3000))
    net = DetectorNet(TINY_DET)
    opt = torch.optim.AdamW(net.parameters())
    return {
        "pose": _pose(tmp_path / "model.pt"),
        "baseline": _pose(tmp_path / "baseline.pt", "baseline"),
        "detector": _detector(tmp_path / "detector.pt"),
        "detector_training_state": _detector(
            tmp_path / "detector_last.pt", optimizer=opt.state_dict(), step=1
        ),
        "junk": junk,
    }


def _no_unsafe_advice(text: str) -> None:
    assert "weights_only" not in text and "Traceback" not in text, text


def test_every_checkpoint_kind_is_recognised_by_its_header(files, tmp_path):
    for kind in ("pose", "baseline", "detector", "detector_training_state"):
        assert checkpoint_kind(files[kind]) == kind
    assert checkpoint_kind(files["junk"]) == "other"
    torch.save({"a": torch.zeros(2)}, tmp_path / "state_dict.pt")
    assert checkpoint_kind(tmp_path / "state_dict.pt") == "other"
    # detector files written before they had a kind: told apart by their optimizer state
    olds = [
        ("old.pt", {}, "detector"),
        ("old_last.pt", {"optimizer": {}}, "detector_training_state"),
    ]
    for name, extra, kind in olds:
        old = dict(torch.load(files["detector"], weights_only=True), **extra)
        del old["kind"]
        torch.save(old, tmp_path / name)
        assert checkpoint_kind(tmp_path / name) == kind
    (tmp_path / "trunc.pt").write_bytes(files["pose"].read_bytes()[:200])
    with pytest.raises(CheckpointFileError, match="truncated") as e:
        checkpoint_kind(tmp_path / "trunc.pt")
    _no_unsafe_advice(str(e.value))


def test_safe_reading_gives_the_stored_checkpoint(files):
    """Reading without running code gives exactly what the unsafe read gave."""
    ck = read_checkpoint(files["pose"])
    ref = torch.load(files["pose"], map_location="cpu", weights_only=False)
    assert ck.keys() == ref.keys()
    for k, v in ref["model"].items():
        assert torch.equal(ck["model"][k], v)
    assert torch.equal(ck["rng"]["torch"], ref["rng"]["torch"])
    assert ck["rng"]["python"] == ref["rng"]["python"]
    np.testing.assert_array_equal(ck["rng"]["numpy"][1], ref["rng"]["numpy"][1])
    assert ck["rng"]["numpy"][1].dtype == ref["rng"]["numpy"][1].dtype
    assert ck["optimizer"] == ref["optimizer"] and ck["config"] == ref["config"]
    model, _, _ = load_checkpoint(files["baseline"])
    assert type(model).__name__ == "BaselineNet"


def _predict(tmp_path, *args):
    session = tmp_path / "session"
    session.mkdir(exist_ok=True)
    out = tmp_path / "out"
    res = CliRunner().invoke(cli, ["predict", str(session), "-o", str(out), *map(str, args)])
    assert res.exit_code != 0
    assert not out.exists()
    _no_unsafe_advice(res.output)
    return res.output


def test_pose_checkpoint_as_detector(files, tmp_path):
    pose = files["pose"]
    out = _predict(tmp_path, "--model", pose, "--detector", pose)
    assert POSE_AS_DETECTOR.format(pose) in out
    with pytest.raises(DetectorCheckpointError, match="is a pose-network checkpoint") as e:
        Detector.load(pose, option="--detector")
    assert str(e.value) == POSE_AS_DETECTOR.format(pose)
    with pytest.raises(DetectorCheckpointError, match="pose-network checkpoint; expected a det"):
        Detector.load(pose)


def test_detector_checkpoint_as_model(files, tmp_path):
    det = files["detector"]
    assert DETECTOR_AS_MODEL.format(det) in _predict(tmp_path, "--model", det, "--method", "bgsub")
    last = files["detector_training_state"]
    out = _predict(tmp_path, "--model", last, "--method", "bgsub")
    assert f"{last} is a detector training checkpoint (detector_last.pt); --model takes" in out
    with pytest.raises(CheckpointError, match="is a detector checkpoint; expected a pose-network"):
        load_checkpoint(det)
    res = CliRunner().invoke(
        cli, ["eval", str(det), str(files["junk"]), "-o", str(tmp_path / "ev")]
    )
    assert res.exit_code != 0 and f"{det} is a detector checkpoint; CKPT takes a pose" in res.output
    _no_unsafe_advice(res.output)
    res = CliRunner().invoke(
        cli,
        ["eval", str(files["pose"]), str(files["junk"]), "-o", str(tmp_path / "ev"),
         "--baseline", str(det)],
    )  # fmt: skip
    assert res.exit_code != 0 and "; --baseline takes a pose-network checkpoint" in res.output


def test_random_file_as_any_checkpoint(files, tmp_path):
    junk = files["junk"]
    out = _predict(tmp_path, "--model", junk, "--method", "bgsub")
    assert OTHER.format(junk) + "--model takes a pose-network checkpoint" in out
    out = _predict(tmp_path, "--model", files["pose"], "--detector", junk)
    assert OTHER.format(junk) + "--detector takes a detector checkpoint" in out
    for load in (read_checkpoint, Detector.load):
        with pytest.raises(CheckpointFileError, match="not a FreiPose checkpoint") as e:
            load(junk)
        _no_unsafe_advice(str(e.value))
    with pytest.raises(DetectorCheckpointError, match="not a FreiPose checkpoint") as e:
        load_backbone_weights(DetectorNet(TINY_DET), junk)
    _no_unsafe_advice(str(e.value))


def test_resume_checks_the_kind_of_the_checkpoint(files, tmp_path):
    from nn_toydata import toy_samples

    from freipose.detect.train import DetectorTrainConfig, ViewImages, fit
    from freipose.nn.train import train_pose

    run = tmp_path / "run"
    run.mkdir()
    (run / "checkpoint.pt").write_bytes(files["detector"].read_bytes())
    cfg = config_from_dict({"model": {"preset": "tiny"}, "schedule": {"steps": 2}})
    with pytest.raises(CheckpointError) as e:
        train_pose(cfg, run, toy_samples(2), toy_skeleton(), resume=True, progress=False)
    assert str(e.value) == (
        f"{run / 'checkpoint.pt'} is a detector checkpoint; --resume takes a pose-network "
        "checkpoint (`freipose train CONFIG`)"
    )
    # a final detector.pt where the resumable detector_last.pt belongs
    det_run = tmp_path / "det_run"
    det_run.mkdir()
    (det_run / "detector_last.pt").write_bytes(files["detector"].read_bytes())
    views = ViewImages([np.zeros((48, 64, 3), np.uint8)], np.array([[4.0, 4, 30, 30]]))
    dcfg = DetectorTrainConfig(input_size=64, width=0.25, neck_channels=8, steps=2, batch_size=1)
    with pytest.raises(DetectorCheckpointError) as e:
        fit(views, dcfg, "cpu", out_dir=det_run, resume=True, progress=False)
    assert str(e.value) == (
        f"{det_run / 'detector_last.pt'} is a detector checkpoint; --resume takes a detector "
        "training checkpoint (detector_last.pt) (`freipose train CONFIG --stage detector`)"
    )


def test_pretrained_encoder_from_a_pose_checkpoint(files):
    cfg = config_from_dict({"model": {"preset": "tiny", "pretrained": str(files["pose"])}})
    model = build_model(cfg.model, 5)
    ref = read_checkpoint(files["pose"])["model"]
    for k, v in model.encoder.state_dict().items():
        assert torch.equal(v, ref[f"encoder.{k}"])
    bad = config_from_dict({"model": {"preset": "tiny", "pretrained": str(files["detector"])}})
    with pytest.raises(CheckpointFileError, match="; model.pretrained takes a pose-network"):
        build_model(bad.model, 5)
