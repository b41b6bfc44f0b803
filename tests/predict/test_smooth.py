"""Temporal smoothing: lower error than raw, honest 2-sigma bands, filled gaps, no lag."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.io.poses import PoseData, read_poses_h5, write_poses_h5
from freipose.predict.smooth import SmoothingError, smooth_arrays, smooth_poses
from freipose.predict.smooth_filter import NU, SmootherParams

T, K, FPS = 1500, 4, 100.0
GAP = slice(700, 710)


def _session(seed: int = 0):
    """A smooth truth, noise of std 2 mm / sqrt(confidence), 3 % gross outliers, a gap."""
    rng = np.random.default_rng(seed)
    t = np.arange(T) / FPS
    f, ph = rng.uniform(0.2, 2.0, (K, 3, 5)), rng.uniform(0, 2 * np.pi, (K, 3, 5))
    amp = rng.uniform(5, 30, (K, 3, 5))
    truth = (amp * np.sin(2 * np.pi * f * t[:, None, None, None] + ph)).sum(-1)
    conf = rng.uniform(0.2, 1.0, (T, K))
    z = truth + rng.normal(size=(T, K, 3)) * (2.0 / np.sqrt(conf))[..., None]
    out = rng.random((T, K)) < 0.03
    z[out] += rng.normal(0, 40, (int(out.sum()), 3))
    conf[out] = 0.05
    z[GAP, 1] = np.nan
    conf[GAP, 1] = 0
    return truth, z, conf


@pytest.fixture(scope="module")
def smoothed():
    truth, z, conf = _session()
    return truth, z, smooth_arrays(z, conf, np.full(T, 1 / FPS))


def test_error_lower_than_raw(smoothed):
    truth, z, res = smoothed
    raw = np.nanmedian(np.linalg.norm(z - truth, axis=-1))
    err = np.median(np.linalg.norm(res.mean - truth, axis=-1))
    assert err < 0.5 * raw
    vel_true = np.diff(truth, axis=0) * FPS
    vel_raw = np.nanmedian(np.linalg.norm(np.diff(z, axis=0) * FPS - vel_true, axis=-1))
    vel_s = np.median(np.linalg.norm(np.diff(res.mean, axis=0) * FPS - vel_true, axis=-1))
    assert vel_s < 0.5 * vel_raw


def test_two_sigma_coverage(smoothed):
    truth, _, res = smoothed
    inside = np.abs(res.mean - truth) <= 2 * res.std
    assert 0.90 <= inside.mean() <= 0.98
    for k in range(K):
        assert inside[:, k].mean() >= 0.88  # above: an offset the fit cannot rule out


def test_fitted_noise_model(smoothed):
    _, _, res = smoothed
    p = res.params
    # one white scale per keypoint (the confidence does not scale it): the fitted Student-t
    # error's standard deviation against the RMS of the true noise, 2 mm / sqrt(conf) with
    # conf uniform in [0.2, 1]: sqrt(4 ln(5) / 0.8) mm
    assert np.all(p.beta == 0)
    sd = p.sigma0 * np.sqrt(NU / (NU - 2))
    np.testing.assert_allclose(sd, np.sqrt(4 * np.log(5) / 0.8), rtol=0.3)


def test_gap_filled_within_band(smoothed):
    truth, _, res = smoothed
    assert res.filled[GAP, 1].all() and res.filled.sum() == 10
    assert np.isfinite(res.mean).all()
    err = np.abs(res.mean[GAP, 1] - truth[GAP, 1])
    assert (err <= 2 * res.std[GAP, 1]).mean() >= 0.9
    assert res.std[GAP, 1].mean() > res.std[600:690, 1].mean()  # wider where filled


def _correlated(seed: int = 0, n: int = 1000, fps: float = 25.0):
    """Data of the smoother's own model: constant-velocity motion (white acceleration of
    density 500 mm^2/s^3), an error correlated over frames (AR(1), 0.8 per frame, 3 mm),
    1.5 mm white noise over sqrt(confidence), and 1 % gross outliers (60 mm) at full
    confidence."""
    rng = np.random.default_rng(seed)
    h = 1 / fps
    acc = rng.normal(size=(n, 3, 3)) * np.sqrt(500 / h)
    truth = np.cumsum(np.cumsum(acc, axis=0) * h, axis=0) * h
    b = np.zeros(truth.shape)
    b[0] = rng.normal(size=(3, 3)) * 3.0
    for i in range(1, n):
        b[i] = 0.8 * b[i - 1] + np.sqrt(1 - 0.64) * 3.0 * rng.normal(size=(3, 3))
    conf = rng.uniform(0.3, 1.0, (n, 3))
    z = truth + b + rng.normal(size=truth.shape) * (1.5 / np.sqrt(conf))[..., None]
    gross = rng.random((n, 3)) < 0.01
    z[gross] += 60.0 * rng.choice([-1.0, 1.0], (int(gross.sum()), 3))
    conf[gross] = 1.0
    return truth, z, conf, gross


@pytest.fixture(scope="module")
def correlated():
    truth, z, conf, gross = _correlated()
    return truth, z, gross, smooth_arrays(z, conf, np.full(len(z), 1 / 25.0))


def test_correlated_error_kept_gross_outliers_left_out(correlated):
    truth, z, gross, res = correlated
    assert res.rejected[gross].mean() >= 0.9
    assert res.rejected[~gross].mean() < 0.005  # a gate on the white noise rejected ~10 %
    assert (res.weight[~gross] > 0.3).mean() > 0.97
    err = np.linalg.norm(res.mean - truth, axis=-1)
    assert np.median(err[gross]) < 2 * np.median(err[~gross])


def test_correlated_error_lower_error_and_honest_band(correlated):
    truth, z, gross, res = correlated
    raw = np.linalg.norm(z - truth, axis=-1)[~gross]
    err = np.linalg.norm(res.mean - truth, axis=-1)[~gross]
    assert np.median(err) < np.median(raw) and err.mean() < raw.mean()
    vt = np.diff(truth, axis=0)
    v_raw = np.median(np.linalg.norm(np.diff(z, axis=0) - vt, axis=-1))
    assert np.median(np.linalg.norm(np.diff(res.mean, axis=0) - vt, axis=-1)) < 0.6 * v_raw
    # the fitted band covers most of the correlated error the recording reveals ...
    assert (np.abs(res.mean - truth) <= 2 * res.std).mean() > 0.75


def test_band_honest_with_the_model_parameters():
    """... and with the parameters that made the data the band has its nominal coverage."""
    truth, z, conf, _ = _correlated(seed=1)
    params = SmootherParams(*(np.full(3, v) for v in (500.0, 1.5, 1.0, 3.0, 0.04 / np.log(1.25))))
    res = smooth_arrays(z, conf, np.full(len(z), 1 / 25.0), params=params)
    inside = np.abs(res.mean - truth) <= 2 * res.std
    assert 0.92 <= inside.mean() <= 0.98


def test_no_lag(smoothed):
    truth, _, res = smoothed
    lags = np.arange(-5, 6)
    for k in range(K):
        a = np.diff(truth[:, k, 0])
        b = np.diff(res.mean[:, k, 0])
        cc = [np.dot(a[10:-10], np.roll(b, lag)[10:-10]) for lag in lags]
        assert lags[int(np.argmax(cc))] == 0


def test_too_few_frames_refused():
    z = np.full((20, 2, 3), np.nan)
    z[:, 0] = 1.0
    z[:2, 1] = 1.0
    with pytest.raises(SmoothingError, match=r"keypoints \[1\] have fewer than 3"):
        smooth_arrays(z, np.ones((20, 2)), np.full(20, 0.01))


def _poses_file(path, n=300):
    truth, z, conf = _session(1)
    data = PoseData(
        poses=z[:n].astype(np.float32),
        confidence=conf[:n].astype(np.float32),
        keypoints=("a", "b", "c", "d"),
        frame_index=np.arange(n),
        fps=FPS,
        provenance={"session": "rec1"},
    )
    write_poses_h5(data, path)
    return data


def test_smooth_poses_schema_and_provenance(tmp_path):
    data = _poses_file(tmp_path / "rec1.poses.h5")
    out = smooth_poses(data, source="rec1.poses.h5")
    assert out.poses.shape == data.poses.shape and np.isfinite(out.poses).all()
    np.testing.assert_array_equal(out.confidence, data.confidence)
    assert out.extra["smooth_std"].shape == (300, K, 3)
    assert out.extra["filled"].dtype == bool
    prov = out.provenance["smoother"]
    assert prov["source"] == "rec1.poses.h5" and set(prov["params"]) == {"a", "b", "c", "d"}
    assert out.provenance["session"] == "rec1"


def test_cli_smooth(tmp_path):
    src = tmp_path / "rec1.poses.h5"
    _poses_file(src)
    run = CliRunner().invoke(cli, ["smooth", str(src), "-o", str(tmp_path / "s")])
    assert run.exit_code == 0, run.output
    dst = tmp_path / "s" / "rec1.poses.h5"
    back = read_poses_h5(dst)
    assert back.extra["filled"].shape == (300, K)
    assert "smoother" in back.provenance
    again = CliRunner().invoke(cli, ["smooth", str(src), "-o", str(tmp_path / "s")])
    assert again.exit_code != 0 and "--overwrite" in again.output
    same = CliRunner().invoke(cli, ["smooth", str(src), "-o", str(tmp_path)])
    assert same.exit_code != 0 and "replace their input" in same.output


def test_predict_smooth_refuses_a_shard(tmp_path):
    model = tmp_path / "model.pt"
    model.write_bytes(b"x")
    run = CliRunner().invoke(
        cli, ["predict", str(tmp_path), "--model", str(model), "-o", str(tmp_path / "o"),
              "--shard", "0/2", "--smooth"],
    )  # fmt: skip
    assert run.exit_code != 0 and "freipose merge" in run.output


def test_predict_smooth_after_prediction(tmp_path):
    from predict_helpers import BlobEstimator, make_session

    from freipose.cli.predict import _smooth_results
    from freipose.io.session import discover_sessions
    from freipose.predict.run import predict_session

    make_session(tmp_path / "rec", 24)
    (s,) = discover_sessions([tmp_path / "rec"])
    res = predict_session(s, BlobEstimator(), tmp_path / "poses", batch_size=4, progress=False)
    _smooth_results([res], tmp_path / "poses", overwrite=False)
    out = tmp_path / "poses" / "smoothed" / "rec.poses.h5"
    assert read_poses_h5(out).extra["smooth_std"].shape[0] == 24
    before = out.stat().st_mtime_ns
    again = predict_session(s, BlobEstimator(), tmp_path / "poses", batch_size=4, progress=False)
    assert again.skipped
    _smooth_results([again], tmp_path / "poses", overwrite=False)
    assert out.stat().st_mtime_ns == before  # kept: the prediction was kept


def test_error_floor_restores_coverage_of_a_bias():
    truth, z, conf = _session(2)
    bias = np.array([8.0, 0.0, 0.0])  # a persistent error the recording cannot reveal
    res = smooth_arrays(z + bias, conf, np.full(T, 1 / FPS))
    err = np.abs(res.mean - truth)
    assert (err <= 2 * res.std).mean() < 0.8
    from freipose.predict.smooth_error import fit_error_floor

    floor = fit_error_floor(res.mean, res.std, truth)
    std = np.sqrt(res.std**2 + floor[None, :, None] ** 2)
    assert abs((err <= 2 * std).mean() - 0.954) < 0.02
    assert np.all(fit_error_floor(truth, np.full_like(truth, 1.0), truth) == 0)


def test_smoothed_names():
    from pathlib import Path

    from freipose.cli.smooth import smoothed_name

    assert smoothed_name(Path("a/rec1.poses.h5.partial")) == "rec1.poses.h5"
    assert smoothed_name(Path("rec1.poses.h5")) == "rec1.poses.h5"
    assert smoothed_name(Path("rec1.nc")) == "rec1.poses.h5"  # a movement dataset in
