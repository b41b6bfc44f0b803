"""Study design (``freipose analyze design``), the synthetic study presets, the 2x2 test and
the null-study benchmark."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from freipose.analysis.config import AttributionConfig
from freipose.analysis.design import pilot_trials, power_table, recommended
from freipose.analysis.io import cached_variables
from freipose.analysis.stats import chi2_pvalue
from freipose.analysis.study import StudyError, load_study
from freipose.analysis.variables import VariableConfig
from freipose.cli.main import cli
from freipose.io.poses import read_poses_h5
from freipose.synth.study import STUDY_PRESETS, StudyPreset, ar1_error, write_study

ROOT = Path(__file__).resolve().parents[2]
PAW = "floor_dist_stft_4.69Hz[Paw Front Right]"
CFG = AttributionConfig(onset_delay_s=0.6, margin_s=0.5)
VCFG = VariableConfig(stft_window=32)


def test_chi2_pvalue_is_scipys_yates_corrected_test():
    from scipy.stats import chi2_contingency

    rng = np.random.default_rng(0)
    for _ in range(200):
        table = rng.integers(1, 80, (2, 2)).astype(float) * rng.uniform(0.2, 1.0)
        assert chi2_pvalue(table) == pytest.approx(chi2_contingency(table).pvalue, rel=1e-9)
    assert chi2_pvalue(np.array([[5.0, 0.0], [7.0, 0.0]])) == 1.0  # a column empty


@pytest.fixture(scope="module")
def pilot(tmp_path_factory):
    """The `pilot` preset (the demo's design: one animal, a train and a test day) and its
    variables."""
    folder = tmp_path_factory.mktemp("pilot")
    path = write_study(folder, STUDY_PRESETS["pilot"], seed=1)
    study = load_study(path)
    variables = {r.name: cached_variables(r.poses, folder / f"{r.name}.vars.h5", None,
                                          "world", VCFG) for r in study.recordings}  # fmt: skip
    return path, study, variables


def test_pilot_trials_measure_the_stimulated_paws_effect(pilot):
    _, study, variables = pilot
    paw = pilot_trials(study, variables, PAW, CFG)
    tail = pilot_trials(study, variables, "floor_dist[Tail]", CFG)
    assert len(paw.trials) == 14 and paw.per_recording == 7 and paw.n_tested == 528
    assert paw.mean_effect > 1.0  # the paw oscillates at 5 Hz during every window
    assert abs(tail.mean_effect) < 0.5 * paw.mean_effect
    with pytest.raises(StudyError, match="close names: ") as err:
        pilot_trials(study, variables, "floor_dist_stft_4.7Hz[Paw Front Right]", CFG)
    assert PAW in str(err.value)


def test_power_grows_with_trials_and_vanishes_without_an_effect(pilot):
    _, study, variables = pilot
    paw = pilot_trials(study, variables, PAW, CFG)
    table = power_table(paw, (4, 56), (1, 2), simulations=20, config=CFG, seed=0)
    power = table.set_index(["trials", "animals"])["power"]
    assert power[(4, 1)] == 0.0  # 2 test trials can never reach p < 0.001 / 528
    assert power[(56, 1)] >= 0.7 and power[(56, 2)] <= power[(56, 1)]
    assert (table["power_low"] <= table["power"]).all()
    assert (table["power"] <= table["power_high"]).all()
    assert recommended(table, 0.7)[1] == 56
    none = power_table(paw, (56,), (1,), effect=0.0, simulations=20, config=CFG, seed=1)
    assert none["power"].iloc[0] <= 0.1
    with pytest.raises(StudyError, match="at least 2 trials per animal"):
        power_table(paw, (1, 8), (1,), simulations=5, config=CFG)


def test_design_command_writes_the_table_and_refuses_unknown_variables(pilot, tmp_path):
    path = pilot[0]
    args = ["analyze", "design", str(path), "-o", str(tmp_path / "d"), "--stft-window", "32",
            "--onset-delay", "0.6", "--margin", "0.5", "--simulations", "10",
            "--trials", "4,14", "--animals", "1"]  # fmt: skip
    res = CliRunner().invoke(cli, [*args, "--variable", PAW])
    assert res.exit_code == 0, res.output
    assert "pilot: 14 trials of 1 animal(s)" in res.output and "Bonferroni over 528" in res.output
    table = pd.read_csv(tmp_path / "d" / "design.csv")
    assert table["trials"].tolist() == [4, 14] and (tmp_path / "d" / "design.png").is_file()
    res = CliRunner().invoke(cli, [*args, "--variable", "paw"])
    assert res.exit_code != 0 and "no variable 'paw' among the 528 variables" in res.output
    assert "Traceback" not in res.output
    res = CliRunner().invoke(cli, [*args[:-4], "--trials", "1,x", "--variable", PAW])
    assert res.exit_code != 0 and "whole numbers separated by commas" in res.output


def test_study_preset_writes_a_valid_study_with_the_error_model(tmp_path):
    preset = dataclasses.replace(STUDY_PRESETS["study"], animals=2, days=3, train_days=2,
                                 frames=250)  # fmt: skip
    path = write_study(tmp_path / "noisy", preset, seed=3)
    study = load_study(path)
    assert [(r.animal, r.split) for r in study.recordings] == [
        ("rat1", "train"), ("rat1", "train"), ("rat1", "test"),
        ("rat2", "train"), ("rat2", "train"), ("rat2", "test"),
    ]  # fmt: skip
    truth = write_study(tmp_path / "truth", preset, seed=3, with_error=False)
    a = read_poses_h5(path.parent / "rat1_day1.poses.h5").poses
    b = read_poses_h5(truth.parent / "rat1_day1.poses.h5").poses
    err = np.linalg.norm(a - b, axis=-1)
    assert 2.5 < float(np.median(err)) < 10.0  # the demo network's 5 mm, as a scale
    assert preset.trials_per_recording == 2
    with pytest.raises(Exception, match="train_days"):
        StudyPreset("x", 1, 2, 2, 100, 25.0, STUDY_PRESETS["study"].stimulation)


def test_ar1_error_persists_over_frames():
    e = ar1_error((20000, 2), 3.0, 5.0, np.random.default_rng(0))
    lag1 = float(np.corrcoef(e[1:, 0], e[:-1, 0])[0, 1])
    assert 2.5 < float(e.std()) < 3.5 and 0.7 < lag1 < 0.9  # exp(-1/5) = 0.82


@pytest.mark.slow
def test_null_benchmark_runs_and_records(tmp_path):
    env = {**os.environ, "FREIPOSE_RESULTS_DIR": str(tmp_path), "OMP_NUM_THREADS": "1"}
    script = ROOT / "benchmarks" / "null_studies.py"
    out = subprocess.run([sys.executable, str(script), "--studies", "2", "--pool", "4"],
                         cwd=ROOT / "benchmarks", env=env, capture_output=True, text=True,
                         timeout=600)  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "family-wise false-positive rate at level 0.001: " in out.stdout
    (record,) = (tmp_path / "null_studies").glob("*.json")
    figures = json.loads(record.read_text())["figures"]
    assert (
        figures["studies"] == 2
        and json.loads(record.read_text())["extra"]["pool"] == 4
        and 0.0 <= figures["fwer_at_alpha"] <= 1.0
    )
    bad = subprocess.run([sys.executable, str(script), "--pool", "3"], cwd=ROOT / "benchmarks",
                         env=env, capture_output=True, text=True)  # fmt: skip
    assert bad.returncode != 0 and "--pool must be 0 or at least 2 x --animals" in bad.stderr


def test_simulate_command_writes_a_study_preset(tmp_path):
    res = CliRunner().invoke(cli, ["analyze", "simulate", str(tmp_path / "s"), "--preset",
                                   "pilot", "--true-poses", "--seed", "2"])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "1 animal(s) x 2 recordings of 30 s (1 train, 1 test per animal), true poses" in (
        res.output
    )
    study = load_study(tmp_path / "s" / "study.toml")
    assert [r.split for r in study.recordings] == ["train", "test"]
    res = CliRunner().invoke(cli, ["analyze", "simulate", str(tmp_path / "t"), "--preset", "x"])
    assert res.exit_code != 0 and "'x' is not one of 'pilot', 'study'" in res.output
