"""Honest bands: the network's error on held-out labels added to the smoother's std."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.io.poses import PoseData, write_poses_h5
from freipose.predict.smooth import smooth_arrays, smooth_poses
from freipose.predict.smooth_error import ValidationLabelsError, predicted_by, validation_error

T, K, FPS = 1000, 3, 25.0
NAMES = ("a", "b", "c")
SCALE = np.array([4.0, 8.0, 14.0])  # per-keypoint std (mm) of the slowly varying error


def _slow_error(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, K, 3) error that varies over about a second (AR(1), 0.96 per frame) + 1 mm noise."""
    e = np.zeros((n, K, 3))
    e[0] = rng.normal(size=(K, 3))
    for t in range(1, n):
        e[t] = 0.96 * e[t - 1] + np.sqrt(1 - 0.96**2) * rng.normal(size=(K, 3))
    return e * SCALE[None, :, None] + rng.normal(size=(n, K, 3))


def _truth(rng: np.random.Generator, n: int) -> np.ndarray:
    t = np.arange(n) / FPS
    f, ph = rng.uniform(0.1, 1.0, (K, 3, 3)), rng.uniform(0, 2 * np.pi, (K, 3, 3))
    return (20 * np.sin(2 * np.pi * f * t[:, None, None, None] + ph)).sum(-1)


@pytest.fixture(scope="module")
def held_out():
    """The error on 40 held-out instants of another recording of the same network."""
    rng = np.random.default_rng(1)
    truth = _truth(rng, 4000)
    pred = truth + _slow_error(rng, 4000)
    idx = np.linspace(0, 3999, 40).round().astype(int)
    return validation_error(pred[idx], truth[idx], NAMES, "test")


def test_held_out_error_makes_the_band_honest(held_out):
    rng = np.random.default_rng(2)
    truth = _truth(rng, T)
    z = truth + _slow_error(rng, T)
    res = smooth_arrays(z, rng.uniform(0.3, 1.0, (T, K)), np.full(T, 1 / FPS))
    err = np.abs(res.mean - truth)
    assert (err <= 2 * res.std).mean() < 0.6  # the recording alone cannot see the slow error
    std = np.sqrt(res.std**2 + held_out.for_keypoints(NAMES)[None] ** 2)
    for k in range(K):
        cov = [(err[:, k] <= m * std[:, k]).mean() for m in (1, 2, 3)]
        print(f"keypoint {NAMES[k]}: coverage at 1/2/3 sigma {cov}")
        assert 0.55 <= cov[0] <= 0.85 and 0.90 <= cov[1] <= 0.99 and cov[2] >= 0.97, cov


def test_held_out_error_values_and_checks():
    pred = np.zeros((6, 2, 3))
    truth = np.zeros((6, 2, 3))
    truth[:, 0, 0] = [1, -1, 1, -1, 1, -1]
    truth[0, 1] = np.nan
    e = validation_error(pred, truth, ("x", "y"))
    np.testing.assert_allclose(e.rms[0], [1, 0, 0])
    assert e.count.tolist() == [6, 5]
    np.testing.assert_allclose(e.for_keypoints(("y", "x"))[1], [1, 0, 0])
    with pytest.raises(ValidationLabelsError, match=r"no keypoints \['z'\]"):
        e.for_keypoints(("x", "z"))
    truth[1:3, 1] = np.nan
    with pytest.raises(ValidationLabelsError, match="fewer than 5 labeled"):
        validation_error(pred, truth, ("x", "y"))


def _poses(path, sha="abc", refine=True):
    rng = np.random.default_rng(3)
    truth = _truth(rng, 200)
    data = PoseData(
        poses=(truth + rng.normal(size=truth.shape)).astype(np.float32),
        confidence=np.full((200, K), 0.8, np.float32),
        keypoints=NAMES,
        frame_index=np.arange(200),
        fps=FPS,
        provenance={"model_sha256": sha, "model_file": "model.pt", "refine": refine},
    )
    write_poses_h5(data, path)
    return data


def test_smooth_poses_records_the_held_out_error(tmp_path, held_out):
    data = _poses(tmp_path / "r.poses.h5")
    plain = smooth_poses(data)
    out = smooth_poses(data, error_floor=held_out)
    want = np.sqrt(plain.extra["smooth_std"] ** 2 + held_out.rms[None] ** 2)
    np.testing.assert_allclose(out.extra["smooth_std"], want, rtol=1e-5)
    per = out.provenance["smoother"]["persistent_error"]
    assert per["kind"] == "error on held-out labels" and set(per["rms_mm"]) == set(NAMES)
    assert "persistent_error" not in plain.provenance["smoother"]


def test_same_model_checked(tmp_path):
    from freipose.predict.network import file_sha256

    model = tmp_path / "model.pt"
    model.write_bytes(b"weights")
    a = tmp_path / "a.poses.h5"
    _poses(a, sha=file_sha256(model), refine=False)
    assert predicted_by([a], model).refine is False
    b = tmp_path / "b.poses.h5"
    _poses(b, sha="0" * 64)
    with pytest.raises(ValidationLabelsError, match="pass the checkpoint that predicted the poses"):
        predicted_by([a, b], model)


def test_cli_validation_needs_model(tmp_path):
    src = tmp_path / "r.poses.h5"
    _poses(src)
    labels = tmp_path / "eval.h5"
    labels.write_bytes(b"x")
    run = CliRunner().invoke(
        cli, ["smooth", str(src), "-o", str(tmp_path / "s"), "--validation", str(labels)]
    )
    assert run.exit_code != 0 and "--validation and --model go together" in run.output
    assert not (tmp_path / "s" / "r.poses.h5").exists()
