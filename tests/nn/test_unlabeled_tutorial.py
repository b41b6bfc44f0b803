"""Every command of ``docs/tutorials/few-labels.md``, run after those of ``docs/own-data.md``.

The tutorial continues the own-rig page, so it runs in a copy of the folder where the
page's commands ran (``own_data_run`` in ``tests/conftest.py``), with the tutorial's fenced
blocks as written after the substitutions below, which only shrink sizes. Each
substitution must match the page, so the test follows it when it changes.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner
from doc_pages import run_blocks, substituted

from freipose.io.poses import read_poses_h5
from freipose.nn.checkpoint import validation_record

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "tutorials" / "few-labels.md"

SUBSTITUTIONS = {
    'preset = "small"': 'preset = "tiny"',
    "steps = 600": "steps = 3",
    "checkpoint_every = 200": "checkpoint_every = 3",
    "eval_every = 200": "eval_every = 3",
    "--n 20": "--n 3",
}


@pytest.mark.slow
def test_few_labels_tutorial_commands(own_data_run, tmp_path, monkeypatch):
    text = substituted(PAGE, SUBSTITUTIONS)
    shutil.copytree(own_data_run["folder"], tmp_path / "own")
    monkeypatch.chdir(tmp_path / "own")
    # the rig's calibration beside the session's videos, as the tutorial asks
    Path("rec/mouse1/calibration.toml").write_text(Path("calibration.toml").read_text())
    Path("next_frames.csv").unlink()  # the own-rig page's proposal: the tutorial writes its own
    outputs, _ = run_blocks(text, CliRunner())
    log = Path("runs/pose_unlabeled/log.csv").read_text().splitlines()
    header = log[0].split(",")
    last = dict(zip(header, log[-1].split(",")))
    assert float(last["u_multiview"]) > 0 and float(last["u_equivariance"]) >= 0
    rec = validation_record("runs/pose_unlabeled/model.pt")
    assert rec["instants"] > 0 and set(rec["chosen"]) == {"map_window", "fusion_reject"}
    assert "validation instants" in outputs["eval runs/pose_unlabeled/model.pt"]
    metrics = json.loads(Path("eval_unlabeled/metrics.json").read_text())
    assert metrics["voxel_P1"]["inference_settings"]["validation"]["instants"] == rec["instants"]
    poses = read_poses_h5("poses_unlabeled/mouse1.poses.h5")
    assert poses.extra["uncertainty"].shape == poses.confidence.shape
    assert Path("next_frames.csv").read_text().startswith("session,frame_index")
