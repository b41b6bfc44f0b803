"""End to end with the real network: a tiny model trained on a toy animal predicts a
synthetic session through ``freipose predict``; resume and shards with the network; wrong
checkpoints and skeletons fail before any work."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from predict_helpers import TOY_KEYPOINTS, h5_equal, toy_rig, toy_session, toy_training_samples

from freipose.cli.main import cli
from freipose.io.poses import read_poses_h5
from freipose.io.session import discover_sessions
from freipose.predict.merge import merge_shards
from freipose.predict.network import (
    DetectorSpec,
    NetworkEstimator,
    file_sha256,
    load_model,
    make_box_source,
)
from freipose.predict.run import predict_session
from freipose.skeleton import Skeleton

T = 24


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """(model.pt, session folder, true poses (T, 5, 3)) of a tiny network trained 100 steps."""
    from freipose.nn.config import config_from_dict
    from freipose.nn.train import train_pose

    root = tmp_path_factory.mktemp("net")
    rig = toy_rig()
    cfg = config_from_dict(
        {
            "model": {"preset": "tiny", "cube_size": 300.0},
            "schedule": {"steps": 100, "lr": 3e-3, "checkpoint_every": 100, "eval_every": 100},
            "augment": {"enabled": False},
        }
    )
    torch.manual_seed(0)
    model = train_pose(
        cfg, root / "run", toy_training_samples(16, rig), Skeleton("toy", TOY_KEYPOINTS),
        progress=False,
    )  # fmt: skip
    truth = toy_session(root / "toy", rig, T)
    return model, root / "toy", truth


def _run(args):
    res = CliRunner().invoke(cli, args, catch_exceptions=False)
    return res


def test_predict_command_end_to_end(trained, tmp_path):
    model, session, truth = trained
    out = tmp_path / "out"
    args = ["predict", str(session), "--model", str(model), "--method", "bgsub", "-o", str(out),
            "--device", "cpu", "--batch", "4"]  # fmt: skip
    res = _run(args)
    assert res.exit_code == 0, res.output
    assert "24 predicted" in res.output
    d = read_poses_h5(out / "toy.poses.h5")
    assert d.keypoints == TOY_KEYPOINTS and d.poses.shape == (T, 5, 3)
    assert d.provenance["model_sha256"] == file_sha256(model)
    assert d.provenance["detection"] == "bgsub" and d.provenance["refine"] is True
    assert d.skeleton is not None and d.skeleton.name == "toy"
    assert np.isfinite(d.poses).all() and (d.confidence > 0).all()
    err = np.linalg.norm(d.poses - truth, axis=-1)
    # a guess of the detected centre for every keypoint, for comparison
    naive = np.linalg.norm(d.extra["center"][:, None, :] - truth, axis=-1)
    jpe = float(np.median(err))
    print(
        f"tiny model, toy session: median JPE {jpe:.1f} mm (centre guess {np.median(naive):.1f} mm)"
    )
    # the tiny model after 100 steps is crude; it must beat the centre guess, and the
    # detected centre must sit on the animal (a geometry bug breaks both)
    assert jpe < 0.85 * float(np.median(naive))
    centre_err = np.linalg.norm(d.extra["center"] - truth.mean(1), axis=-1)
    assert np.median(centre_err) < 35.0
    inside = np.abs(d.poses - d.extra["center"][:, None, :]) <= 150.0 + 1e-3
    assert inside.all()  # soft-argmax stays inside the 300 mm cube
    boxes = d.extra["boxes"]
    assert boxes.shape == (T, 3, 4) and np.isfinite(boxes).all()
    assert np.isfinite(d.extra["points2d"]).all()
    # the same command again skips the finished output
    res2 = _run(args)
    assert res2.exit_code == 0 and "skipped" in res2.output


def test_network_resume_and_shards_equal_single_run(trained, tmp_path):
    model_path, session, _ = trained
    (s,) = discover_sessions([session])
    net, cfg, skel, sha = load_model(model_path, "cpu")
    spec = DetectorSpec("bgsub", bg_samples=12)
    source = make_box_source(spec, s, (0, T), "cpu")
    prov = {"model_sha256": sha, **spec.describe()}

    def est():
        return NetworkEstimator(net, cfg, skel, source, True, prov)

    kw = dict(batch_size=4, chunk_frames=8, progress=False, skeleton=skel)
    ref = predict_session(s, est(), tmp_path / "ref", **kw).path

    class Killed(Exception):
        pass

    def kill(rows):
        if rows >= 12:
            raise Killed

    with pytest.raises(Killed):
        predict_session(s, est(), tmp_path / "resumed", on_batch=kill, **kw)
    res = predict_session(s, est(), tmp_path / "resumed", **kw)
    assert res.frames == T - 8
    assert h5_equal(res.path, ref) == []
    parts = [predict_session(s, est(), tmp_path / "sh", shard=(i, 2), **kw).path for i in range(2)]
    merged = merge_shards(parts, tmp_path / "sh" / "toy.poses.h5")
    assert h5_equal(merged, ref) == []


def test_untrained_detector_runs_and_keeps_every_frame(trained, tmp_path):
    from freipose.detect.detector import save_checkpoint
    from freipose.detect.model import DetectorConfig, DetectorNet

    model, session, _ = trained
    torch.manual_seed(0)
    det = tmp_path / "det.pt"
    save_checkpoint(det, DetectorNet(DetectorConfig(input_size=64, width=0.25, neck_channels=8)))
    out = str(tmp_path / "o")
    res = _run(["predict", str(session), "--model", str(model), "--detector", str(det),
                "-o", out, "--device", "cpu", "--frames", "0:8", "--no-refine"])  # fmt: skip
    assert res.exit_code == 0, res.output
    d = read_poses_h5(tmp_path / "o" / "toy.poses.h5")
    assert d.num_frames == 8 and d.provenance["detection"] == "detector"
    assert d.provenance["detector_sha256"] == file_sha256(det)
    lost = ~np.isfinite(d.extra["center"]).all(-1)
    assert np.all(np.isnan(d.poses[lost])) and np.all(d.confidence[lost] == 0)
    assert np.all(d.extra["status"][lost] == 1) and np.all(d.extra["status"][~lost] == 0)


def test_wrong_checkpoints_and_skeleton_fail_before_work(trained, tmp_path):
    from freipose.detect.detector import save_checkpoint
    from freipose.detect.model import DetectorConfig, DetectorNet

    model, session, _ = trained
    det = tmp_path / "det.pt"
    save_checkpoint(det, DetectorNet(DetectorConfig(input_size=64, width=0.25, neck_channels=8)))
    out = tmp_path / "o"
    base = ["predict", str(session), "-o", str(out), "--device", "cpu"]
    res = _run([*base, "--model", str(det), "--method", "bgsub"])
    expected = "is a detector checkpoint; --model takes a pose-network checkpoint"
    assert res.exit_code != 0 and expected in res.output
    res = _run([*base, "--model", str(model), "--detector", str(model)])
    assert res.exit_code != 0 and "detector checkpoint" in res.output
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    res = _run([*base, "--model", str(junk), "--method", "bgsub"])
    assert res.exit_code != 0 and "junk.pt" in res.output
    res = _run([*base, "--model", str(model), "--method", "bgsub", "--skeleton", "rat"])
    assert res.exit_code != 0 and "trained for keypoints" in res.output
    res = _run([*base, "--model", str(model), "--method", "detector"])  # (no option: auto)
    assert res.exit_code != 0 and "--detector CKPT" in res.output
    assert not out.exists() or not any(out.iterdir())


def test_predict_inference_settings_are_recorded_and_smoothing_matches_them(trained, tmp_path):
    from freipose.nn.config import InferenceOverrides
    from freipose.predict.smooth_error import ValidationLabelsError, predicted_by

    model, session, _ = trained
    base = ["predict", str(session), "--model", str(model), "--method", "bgsub", "--device",
            "cpu", "--batch", "4", "--frames", "0:8"]  # fmt: skip
    runs = {
        "every": ["--fusion-reject", "0"],
        "near": ["--fusion-reject", "0.2"],
        "whole": ["--fusion-reject", "0.2", "--map-window", "0"],
    }
    for name, options in runs.items():
        res = _run([*base, "-o", str(tmp_path / name), *options])
        assert res.exit_code == 0, res.output
    every, near, whole = (tmp_path / name / "toy.poses.h5" for name in runs)
    window = read_poses_h5(every).provenance["map_window"]  # the checkpoint's own
    assert read_poses_h5(every).provenance["fusion_reject"] == 0.0
    assert read_poses_h5(near).provenance["fusion_reject"] == pytest.approx(0.2)
    assert read_poses_h5(whole).provenance["map_window"] == 0 != window
    assert predicted_by([near, near], model).overrides == InferenceOverrides(0.2, int(window))
    assert predicted_by([whole], model).overrides == InferenceOverrides(0.2, 0)
    with pytest.raises(ValidationLabelsError, match="different --fusion-reject"):
        predicted_by([every, near], model)
    with pytest.raises(ValidationLabelsError, match="different --map-window"):
        predicted_by([near, whole], model)
    for option in ("--fusion-reject", "--map-window"):
        res = CliRunner().invoke(cli, [*base, "-o", str(tmp_path / "bad"), option, "-1"])
        said = "must be >= 0" in res.output or "must be in [0, 1000]" in res.output
        assert res.exit_code != 0 and said, res.output
