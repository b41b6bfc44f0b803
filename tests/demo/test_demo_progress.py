"""A piped ``freipose demo`` prints a line at least every 30 s of training and prediction.

The shared tiny demo (``conftest.py``) runs in a subprocess whose standard output and
error go to a pipe (as under nohup or in a cluster job's log); the arrival time of every
line is recorded.
"""

from __future__ import annotations

import json
import re

import pytest

from freipose.demo.markers import STEPS

MAX_GAP_S = 30.0


def _header(lines, step):
    """The index of the demo's header line of ``step``."""
    i = STEPS.index(step) + 1
    return next(j for j, (_, ln) in enumerate(lines) if ln.startswith(f"[{i}/{len(STEPS)}]"))


@pytest.mark.slow
def test_piped_demo_prints_progress_during_training_and_prediction(tiny_demo_lines):
    out, lines = tiny_demo_lines
    text = "\n".join(ln for _, ln in lines)
    first, last = _header(lines, "train"), _header(lines, "evaluate")
    window = lines[first : last + 1]
    gaps = [b[0] - a[0] for a, b in zip(window, window[1:])]
    worst = max(range(len(gaps)), key=gaps.__getitem__)
    assert gaps[worst] < MAX_GAP_S, (
        f"{gaps[worst]:.0f} s without output after {window[worst][1]!r}:\n{text}"
    )
    print(
        f"largest gap {gaps[worst]:.1f} s of {window[-1][0] - window[0][0]:.0f} s (train, predict)"
    )
    bars = [ln for _, ln in window if re.search(r"\d+/\d+ \w+ \(\d+%\), \d+:\d\d elapsed", ln)]
    assert any(ln.startswith("train voxel") or "step" in ln for ln in bars), text
    assert "\r" not in text  # lines, not a terminal bar
    # the steps ran (not skipped) and wrote their outputs
    assert "train: done earlier" not in text and "predict: done earlier" not in text
    marker = json.loads((out / ".demo" / "predict.done").read_text())
    assert marker["results"]["poses"]


@pytest.mark.slow
def test_demo_evaluate_step_returns_failure_modes_and_references(tiny_demo):
    out, output = tiny_demo
    res = json.loads((out / ".demo" / "evaluate.done").read_text())["results"]
    modes = res["failure_modes"]
    assert {p["left"] for p in modes["pairs"]} >= {"Ear Left", "Paw Front Left"}
    assert all(set(p) >= {"left", "right", "predicted_mm", "true_mm", "swap_rate", "collapsed"}
               for p in modes["pairs"])  # fmt: skip
    assert len(modes["bones"]) == 13 and isinstance(modes["warnings"], list)
    refs = res["references"]
    assert set(refs) == {"median pose at held-out centre", "median pose at training centre"}
    assert all(r["median_mm"] > 0 for r in refs.values())
    for session in res["pipeline"].values():  # every frame of each session, too
        assert len(session["failure_modes"]["pairs"]) == 5
    assert "references that look at no image" in output
    assert "(read: the synthetic generator's labels of every frame" in output
    assert "labels/train.h5 (written: the training labels)" in output
