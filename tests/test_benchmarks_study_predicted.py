"""benchmarks/study_predicted.py: the study preset rendered, predicted and analysed (tiny)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pandas as pd
import pytest

from freipose.synth.study import STUDY_PRESETS, recording_stimulation, write_study

BENCHMARK = "study_predicted"  # the script the conftest fixture ``bench`` loads

STIM = {"duration_s": 0.4, "spacing_s": 0.4, "onset_s": 0.2}
TINY = ["--animals", "1", "--days", "2", "--frames", "50", "--cameras", "2", "--size", "160x128",
        *[a for k, v in STIM.items() for a in ("--stim", f"{k}={v}")],
        "--onset-delay", "0", "--margin", "0.1", "--stft-window", "8", "--executor", "none",
        "--cores", "1", "--design-trials", "2,4", "--simulations", "10",
        "--design-variable", "floor_dist_stft_6.25Hz[Paw Front Right]"]  # fmt: skip


def test_design_days_are_whole_recordings_an_even_number_within_the_preset(bench):
    assert bench.design_days(56, 7, 8) == 8
    assert bench.design_days(42, 7, 8) == 6
    assert bench.design_days(30, 7, 8) == 6  # 5 recordings rounded up to 3 train + 3 test
    assert bench.design_days(70, 7, 8) == 8  # more than the preset holds: all of it
    assert bench.design_days(None, 7, 8) == 8


def test_paw_findings_read_rank_significance_and_attribution_per_animal(bench):
    paw, tail = "Paw Front Right", "Tail"
    rows = [
        ("rat1", "a[paw]", paw, 0.9, 1e-5, True),
        ("rat1", "b[tail]", tail, 0.7, 0.5, False),
        ("rat2", "b[tail]", tail, 0.8, 1e-4, True),
        ("rat2", "a[paw]", paw, 0.75, 1e-4, True),
    ]
    att = pd.DataFrame(rows, columns=["animal", "variable", "part", "f1", "p_adjusted",
                                      "significant"])  # fmt: skip
    out = bench.paw_findings(att)
    one, two = out["animals"]["rat1"], out["animals"]["rat2"]
    assert (one["paw_rank"], one["paw_significant"], one["significant_other"]) == (1, 1, [])
    assert (two["paw_rank"], two["best_part"], two["significant_other"]) == (2, tail, ["b[tail]"])
    assert out["paw_significant_in_every_animal"] and not out["correctly_attributed"]
    assert bench.paw_findings(att[att["animal"] == "rat1"])["correctly_attributed"]


@pytest.fixture(scope="module")
def tiny_run(bench, tmp_path_factory):
    """A tiny study (1 animal, 2 days of 50 frames, 2 cameras) run once, with its pilot."""
    work = tmp_path_factory.mktemp("study_predicted")
    base = STUDY_PRESETS["pilot"]
    pilot = dataclasses.replace(base, frames=50, stimulation={**base.stimulation, **STIM})
    args = [*TINY, "--work", str(work), "--pilot", str(write_study(work / "pilot", pilot))]
    return work, args, bench.main(args)


@pytest.mark.slow
def test_a_tiny_study_is_rendered_with_the_preset_schedules_and_predicted(bench, tiny_run):
    work, _, path = tiny_run
    rec = json.loads(path.read_text())["figures"]
    preset = bench.study_preset(bench.parse_args(TINY))
    assert rec["recordings"] == 2 and rec["trials_per_recording"] == preset.trials_per_recording
    events = []
    for a, d, name in bench.recording_names(preset):
        got = np.loadtxt(work / "recordings" / name / "events.csv", delimiter=",", skiprows=1,
                         ndmin=2)  # fmt: skip
        stim = recording_stimulation(preset, np.random.default_rng(bench.day_seed(a, d)))
        np.testing.assert_allclose(got, stim.windows(preset.frames / preset.fps), atol=1e-6)
        events.append(got)
        err = rec["errors"][name]
        assert 0 < err["jpe_median_mm"] < 30 and 0 < err["found_share"] <= 1
    assert not np.array_equal(events[0], events[1])  # every day its own schedule
    findings = rec["analyses"]["predicted_recommended"]
    assert findings["days_per_animal"] == 2 and set(findings["animals"]) == {"rat1"}
    assert findings["animals"]["rat1"]["paw_rank"] >= 1
    assert {r["animals"] for r in rec["design"]["table"]} == {1}


@pytest.mark.slow
def test_a_rerun_keeps_what_is_rendered_and_predicted(bench, tiny_run, capsys):
    work, args, _ = tiny_run
    poses = sorted((work / "poses").glob("*.poses.h5"))
    before = [p.stat().st_mtime_ns for p in poses]
    capsys.readouterr()
    bench.main(args)
    out = capsys.readouterr().out
    assert out.count("rendered, kept") == 2 and "2 of 2 recordings predicted, kept" in out
    assert [p.stat().st_mtime_ns for p in poses] == before
