"""The demo's explanation of significant variables from the synthetic truth."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np

from freipose.demo import report
from freipose.demo.presets import PRESETS
from freipose.demo.truth_effect import (
    error_inside_outside,
    moved_keypoints,
    truth_note,
    truth_notes,
)

TAIL = {"variable": "floor_dist_stft_3.12Hz[Tail]", "rank": 85, "keypoints": "Tail"}
PAW = {"variable": "local_z[Paw Front Right]", "rank": 1, "keypoints": "Paw Front Right"}


def test_the_stimulation_moves_only_the_stimulated_paw():
    moved = moved_keypoints(PRESETS["tiny"], PRESETS["tiny"].sessions[1].seed)
    assert moved["Paw Front Right"] > 5.0
    assert max(d for k, d in moved.items() if k != "Paw Front Right") == 0.0
    assert moved["Tail"] == 0.0


def test_notes_tell_effects_from_false_positives_and_tracking_errors():
    moved = {"Paw Front Right": 25.5, "Tail": 0.0, "Nose": 0.0}
    assert truth_notes([PAW], moved) == []  # the stimulated paw needs no explanation
    (note,) = truth_notes([PAW, TAIL], moved, {"Tail": (6.2, 4.1)})
    assert note.startswith(
        "floor_dist_stft_3.12Hz[Tail] (rank 85): in the synthetic truth Tail moves the same"
    )
    assert (
        "largest difference 0.00 mm; the stimulation moves only Paw Front Right (up to 25.5 mm)"
        in note
    )
    assert (
        "Tail 6.2 mm in the stimulated frames and 4.1 mm outside: a tracking error that follows"
        in note
    )
    (same,) = truth_notes([TAIL], moved, {"Tail": (4.2, 4.1)})
    assert same.endswith("the error does not follow the stimulation: a false positive of the test.")
    assert truth_note(TAIL, moved).endswith("on the true poses it is a false positive of the test.")
    assert "an effect of the stimulation." in truth_note(PAW, moved)


def test_error_inside_and_outside_the_stimulated_frames():
    truth = np.zeros((6, 2, 3))
    pred = truth.copy()
    pred[:3, 1, 0] = 4.0
    pred[3:, 1, 0] = 1.0
    labels = np.array([1, 1, 1, 0, 0, -1])
    assert error_inside_outside(pred, truth, labels, 1) == (4.0, 1.0)
    assert error_inside_outside(pred, truth, labels, 0) == (0.0, 0.0)


def test_report_prints_the_truth_notes(tmp_path):
    spec = importlib.util.spec_from_file_location(
        "demo_report_fixture", Path(__file__).parent / "test_report.py"
    )
    fixture = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(fixture)
    ctx = fixture._markers(tmp_path / "demo", failure_modes=False, smooth=True)
    marker = tmp_path / "demo" / ".demo" / "analyze.done"
    doc = json.loads(marker.read_text())
    note = truth_note(TAIL, {"Paw Front Right": 25.5, "Tail": 0.0}, {"Tail": (6.2, 4.1)})
    doc["results"]["smoothed"]["truth_notes"] = [note]
    marker.write_text(json.dumps(doc))
    page = Path(report.run(ctx)["report"]).read_text()
    assert "the network&#39;s median error on the test day is Tail 6.2 mm" in page
