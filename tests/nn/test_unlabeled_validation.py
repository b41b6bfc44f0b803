"""Inference settings and the uncertainty's scale chosen on validation labels (tiny preset)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner
from nn_toydata import toy_samples, toy_skeleton, write_toy_labels

from freipose.cli.main import cli
from freipose.nn.checkpoint import load_checkpoint, read_checkpoint, validation_record
from freipose.nn.config import config_from_dict
from freipose.nn.data import collate_prepared, prepare_sample
from freipose.nn.inference import predict_prepared
from freipose.nn.train import train_pose
from freipose.nn.uncertainty import fit_scale, raw_uncertainty, two_sigma_coverage
from freipose.nn.validation import FUSION_REJECTS, MAP_WINDOWS


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny network trained on toy samples with 96 validation instants."""
    out = tmp_path_factory.mktemp("run")
    val = write_toy_labels(tmp_path_factory.mktemp("val"), toy_samples(96, seed=11))
    cfg = config_from_dict(
        {
            "data": {"validation_labels": str(val)},
            "model": {"preset": "tiny", "cube_size": 300.0},
            "schedule": {"steps": 40, "lr": 3e-3, "checkpoint_every": 40, "eval_every": 40},
        }
    )
    path = train_pose(cfg, out, toy_samples(8), toy_skeleton(), progress=False)
    return path, out


def test_eval_labels_alone_do_not_choose_settings(tmp_path):
    """Labels that only monitor training (often the held-out test labels) never tune."""
    cfg = config_from_dict({"model": {"preset": "tiny", "cube_size": 300.0},
                            "schedule": {"steps": 2}})  # fmt: skip
    path = train_pose(cfg, tmp_path, toy_samples(2), toy_skeleton(), toy_samples(4, seed=3),
                      progress=False)  # fmt: skip
    assert validation_record(path) == {}


def test_final_checkpoint_records_the_settings_chosen_on_validation(trained):
    path, out = trained
    rec = validation_record(path)
    assert rec["instants"] == 96
    assert set(rec["tried"]["map_window"]) == {str(v) for v in MAP_WINDOWS}
    assert set(rec["tried"]["fusion_reject"]) == {str(float(v)) for v in FUSION_REJECTS}
    assert rec["configured"] == {"map_window": 3, "fusion_reject": 1.0}
    # the chosen window is the best one tried, or the configured one within 1 %
    tried = rec["tried"]["map_window"]
    chosen = str(rec["chosen"]["map_window"])
    assert tried[chosen] == min(tried.values()) or chosen == "3"
    assert tried[chosen] <= tried["3"]
    _, config, _ = load_checkpoint(path)
    assert config.model.map_window == rec["chosen"]["map_window"]
    assert config.model.fusion_reject == rec["chosen"]["fusion_reject"]
    assert rec["uncertainty_scale"] > 0
    assert 0.9 <= rec["uncertainty_coverage"] <= 1.0
    # the resumable state keeps the configured settings
    assert read_checkpoint(out / "checkpoint.pt")["config"]["model"]["map_window"] == 3
    assert validation_record(out / "checkpoint.pt") == {}


def _sigma(model, config, samples, scale):
    batch = collate_prepared([prepare_sample(s, config.model) for s in samples])
    pred = predict_prepared(model, batch)
    raw = raw_uncertainty(pred["P0"], pred["P1"], pred["points2d"], pred["confidence2d"],
                          batch["rigs"], config.model.voxel_size)  # fmt: skip
    gt = np.stack([s["points3d"] for s in samples])
    return np.linalg.norm(pred["P1"] - gt, axis=-1), raw, scale * raw


def test_two_sigma_coverage_on_held_out_labels(trained):
    path, _ = trained
    model, config, _ = load_checkpoint(path)
    scale = validation_record(path)["uncertainty_scale"]
    err, raw, sigma = _sigma(model, config, toy_samples(60, seed=23), scale)
    coverage = two_sigma_coverage(err, sigma)
    assert 0.90 <= coverage <= 0.98, coverage
    assert np.isfinite(raw).all() and (raw > 0).all()


def test_fit_scale_hits_its_coverage():
    rng = np.random.default_rng(0)
    raw = rng.uniform(1, 5, 2000)
    err = np.abs(rng.normal(0, 3.0 * raw))
    cal = fit_scale(err, raw)
    assert abs(cal.coverage - 0.95) < 0.005 and cal.keypoints == 2000
    assert np.isnan(fit_scale(np.full(3, np.nan), raw[:3]).scale)


def test_eval_reports_the_settings_chosen_on_validation(trained, tmp_path):
    path, _ = trained
    labels = write_toy_labels(tmp_path / "held", toy_samples(4, seed=31))
    res = CliRunner().invoke(cli, ["eval", str(path), str(labels), "-o", str(tmp_path / "ev")])
    assert res.exit_code == 0, res.output
    assert "validation instants" in res.output
    doc = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    rep = doc["voxel_P1"]["inference_settings"]
    assert rep["validation"]["instants"] == 96
    assert rep["used"]["map_window"] == rep["validation"]["chosen"]["map_window"]
    over = ["--map-window", "0", "-o", str(tmp_path / "ev0")]
    res = CliRunner().invoke(cli, ["eval", str(path), str(labels), *over])
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "ev0" / "metrics.json").read_text())
    assert doc["voxel_P1"]["inference_settings"]["used"]["map_window"] == 0


class _CentreBoxes:
    """A box source: every camera's box around the toy animal's arena centre."""

    def __init__(self, rig):
        self.rig = rig

    def propose(self, images, cameras):
        from freipose.detect.base import Candidates
        from freipose.geometry.crops import cube_crop_boxes

        boxes = cube_crop_boxes(self.rig, np.array([0.0, 0, 40]), 200.0)
        by_name = dict(zip(self.rig.names, boxes))
        return [Candidates(by_name[c][None], np.ones(1)) for c in cameras]


def test_predict_writes_the_calibrated_uncertainty_and_select_ranks_by_it(trained, tmp_path):
    from test_unlabeled import _write_session

    from freipose.io.poses import read_poses_h5
    from freipose.io.session import discover_sessions
    from freipose.labels.select import frame_uncertainty, select_frames
    from freipose.predict.network import NetworkEstimator, load_model
    from freipose.predict.run import predict_session

    path, _ = trained
    folder = _write_session(tmp_path / "s", toy_samples(6, seed=41))
    session = discover_sessions([folder], need_fps=False)[0]
    model, config, skel, _ = load_model(path)
    scale = validation_record(path)["uncertainty_scale"]
    est = NetworkEstimator(model, config, skel, _CentreBoxes(session.rig),
                           uncertainty_scale=scale)  # fmt: skip
    res = predict_session(session, est, tmp_path / "out", skeleton=skel, progress=False)
    d = read_poses_h5(res.path)
    u = d.extra["uncertainty"]
    assert u.shape == (6, 5) and np.isfinite(u).all() and (u > 0).all()
    sel = select_frames(d, 2, min_gap=0)
    per_frame = frame_uncertainty(d, np.ones(6, bool))
    assert sel.uncertainty[0] == pytest.approx(per_frame.max())  # the most uncertain first
    # without a calibrated scale the uncertainty is unknown (NaN) and select falls back
    # to the confidences
    est = NetworkEstimator(model, config, skel, _CentreBoxes(session.rig))
    res = predict_session(session, est, tmp_path / "raw", skeleton=skel, progress=False)
    d = read_poses_h5(res.path)
    assert np.isnan(d.extra["uncertainty"]).all()
    sel = select_frames(d, 2, min_gap=0)
    assert np.isnan(sel.uncertainty).all()
    assert sel.confidence[0] == pytest.approx(d.confidence.mean(1).min(), abs=1e-6)
