"""Regression: the full SVM must not collapse to one class when some variables are constant
up to float round-off in the train recording but shifted in the test recording (rigid head
keypoints of a differently sized animal; found in the demo's ground-truth poses)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from freipose.analysis.config import AttributionConfig
from freipose.analysis.simulate import (
    StimulusEffect,
    simulate_rat,
    stimulation_windows,
    write_events_csv,
)
from freipose.analysis.stats import informative_columns, standardize_recording
from freipose.cli.main import cli
from freipose.io.poses import write_poses_h5

STIM_KP = "Paw Front Right"
HEAD = ("Ear Right", "Eye Right", "Ear Left", "Eye Left", "Nose")


def test_informative_columns_drops_round_off_constants():
    rng = np.random.default_rng(0)
    n = 500
    x = np.stack(
        [
            rng.normal(0.0, 1.0, n),  # varies around 0
            (32.7 + rng.normal(0.0, 1e-6, n)).astype(np.float32),  # constant up to round-off
            np.full(n, 5.0),  # exactly constant
            np.full(n, np.nan),  # undefined
            np.where(np.arange(n) % 2, np.nan, 100.0 + rng.normal(0.0, 0.5, n)),  # NaN gaps
            np.zeros(n),
        ],
        axis=1,
    )
    assert informative_columns(x).tolist() == [True, False, False, False, True, False]
    # rtol 0 keeps the round-off column (its deviation is not exactly 0).
    assert informative_columns(x, rtol=0.0)[1]


@pytest.fixture(scope="module")
def short_study(tmp_path_factory):
    """Demo-like study: 30 s at 25 fps per recording, 7 windows of a 5 Hz, 30 mm oscillation
    of the right front paw; 1 mm noise on the body but a rigid, noise-free head (its
    distances to the ear midpoint are constant up to float32 round-off, as in the demo's
    ground truth) and a test animal 12% larger than the train animal."""
    folder = tmp_path_factory.mktemp("short_study")
    fps, dur = 25.0, 30.0
    effect = StimulusEffect(STIM_KP, frequency_hz=5.0, amplitude_mm=30.0, lift_mm=0.0)
    entries = []
    for k, (split, scale) in enumerate((("train", 1.0), ("test", 1.12))):
        win = stimulation_windows(dur, 1.0, 4.0, 2.0, 0.0, seed=k)
        data = simulate_rat(dur, fps, win, effect, seed=k, noise_mm=0.0)
        poses = data.poses.astype(np.float64) * scale
        body = [i for i, n in enumerate(data.keypoints) if n not in HEAD]
        poses[:, body] += np.random.default_rng(k).normal(0.0, 1.0, poses[:, body].shape)
        data = dataclasses.replace(data, poses=poses.astype(np.float32))
        write_poses_h5(data, folder / f"{split}.poses.h5")
        write_events_csv(win, folder / f"{split}_events.csv")
        entries.append(
            f'[[recordings]]\nname = "{split}"\nposes = "{split}.poses.h5"\n'
            f'events = "{split}_events.csv"\nanimal = "rat1"\ncondition = "paw"\n'
            f'split = "{split}"\n'
        )
    study = folder / "study.toml"
    study.write_text("\n".join(entries))
    out = folder / "out"
    args = ["analyze", str(study), "-o", str(out), "--stft-window", "32", "--no-figures"]
    args += ["--onset-delay", "0.6", "--margin", "0.5", "--pre", "1", "--post", "1"]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 0, res.output
    return out


def test_full_classifier_beats_chance_on_short_recordings(short_study):
    cls = pd.read_csv(short_study / "classification.csv")
    assert len(cls) == 1
    row = cls.iloc[0]
    # Before the fix: balanced accuracy 0.5 (every test frame in one class).
    assert row["balanced_accuracy"] > 0.7, row
    assert row["f1"] > 0.7, row
    n_vars = len(pd.read_csv(short_study / "attribution.csv"))
    assert 0 < row["n_variables_used"] < n_vars
    dyn = pd.read_csv(short_study / "dynamics.csv")
    inside = dyn[(dyn["time_s"] > 0.8) & (dyn["time_s"] < 1.9)]["mean_prediction"].mean()
    before = dyn[dyn["time_s"] < -0.2]["mean_prediction"].mean()
    assert inside > before + 0.3, (inside, before)


def test_round_off_constant_variables_are_not_tested(short_study):
    att = pd.read_csv(short_study / "attribution.csv").sort_values("rank")
    untested = att[att["f1"].isna()]
    assert len(untested) > 0
    # The rigid head's distances to the local origin are among them.
    assert untested["variable"].str.startswith("origin_dist[").any(), untested["variable"]
    tested = att["f1"].notna().sum()
    assert np.allclose(att["p_adjusted"], np.minimum(1, att["p_value"] * tested), rtol=1e-4)
    assert att.head(5)["keypoints"].str.contains(STIM_KP).all(), att.head(5)


def test_standardize_recording_and_config_checks():
    rng = np.random.default_rng(1)
    x = np.stack(
        [
            rng.normal(50.0, 3.0, 200),
            np.float32(12.63) + rng.normal(0.0, 1e-6, 200).astype(np.float32),
            np.r_[np.full(20, np.nan), rng.normal(-4.0, 0.5, 180)],
        ],
        axis=1,
    ).astype(np.float32)
    z = standardize_recording(x)
    assert np.allclose(z[:, 0].mean(), 0, atol=1e-9) and np.isclose(z[:, 0].std(), 1)
    assert (z[:, 1] == 0).all()  # round-off constant: no signal, not amplified noise
    assert np.isnan(z[:20, 2]).all() and np.isclose(np.nanstd(z[:, 2]), 1)
    with pytest.raises(ValueError, match="standardize"):
        AttributionConfig(standardize="zscore")
    with pytest.raises(ValueError, match="constant_rtol"):
        AttributionConfig(constant_rtol=-1.0)


def test_full_classifier_is_reproducible():
    """More variables than frames: liblinear's dual solver, whose frame order is seeded."""
    from freipose.analysis.classifier import make_svm

    rng = np.random.default_rng(0)
    X = rng.normal(size=(120, 300))
    y = (X[:, 0] + rng.normal(size=120) > 0).astype(int)
    coefs = [make_svm(1.0, max_iter=50).fit(X, y)[-1].coef_ for _ in range(3)]
    for c in coefs[1:]:
        np.testing.assert_array_equal(c, coefs[0])


def test_classification_reports_the_fit_of_the_train_frames(short_study):
    row = pd.read_csv(short_study / "classification.csv").iloc[0]
    assert row["balanced_accuracy"] <= row["train_balanced_accuracy"] <= 1.0


def test_overfit_note_names_a_perfect_fit_that_does_not_generalise():
    from freipose.analysis.attribution import overfit_note

    att = pd.DataFrame({"variable": ["a", "paw"], "balanced_accuracy": [0.55, 0.83]})
    note = overfit_note({"train_balanced_accuracy": 1.0, "balanced_accuracy": 0.44}, att, 528)
    assert note is not None and "0.44" in note and "paw: 0.83" in note and "528" in note
    # no warning: the fit is imperfect, or the full classifier is near the best variable
    for fit, test, table in ((0.9, 0.44, att), (1.0, 0.76, att), (1.0, 0.5, att[:0])):
        row = {"train_balanced_accuracy": fit, "balanced_accuracy": test}
        assert overfit_note(row, table, 2) is None
