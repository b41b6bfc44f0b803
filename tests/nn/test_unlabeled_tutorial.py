"""Every command of ``docs/tutorials/few-labels.md``, run after those of ``docs/own-data.md``.

The tutorial continues the own-rig page, so the page's commands run first (as
``tests/test_own_data.py`` runs them, with its substitutions), then the tutorial's fenced
blocks as written after the substitutions below, which only shrink sizes. Each
substitution must match the page, so the test follows it when it changes.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.io.poses import read_poses_h5
from freipose.nn.checkpoint import validation_record
from freipose.testing import fenced_blocks, freipose_commands

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "tutorials" / "few-labels.md"

SUBSTITUTIONS = {
    'preset = "small"': 'preset = "tiny"',
    "steps = 600": "steps = 3",
    "checkpoint_every = 200": "checkpoint_every = 3",
    "eval_every = 200": "eval_every = 3",
    "--n 20": "--n 3",
}


def _own_data():
    """``tests/test_own_data.py`` as a module (its page and substitutions)."""
    spec = importlib.util.spec_from_file_location("own_data", ROOT / "tests" / "test_own_data.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _run_page(text: str, runner: CliRunner) -> dict[str, str]:
    outputs: dict[str, str] = {}
    for lang, body, name in fenced_blocks(text):
        if lang == "toml" and name:
            Path(name).write_text(body, encoding="utf-8")
        if lang != "bash":
            continue
        for args in freipose_commands(body):
            res = runner.invoke(cli, args)
            assert res.exit_code == 0, f"freipose {' '.join(args)}\n{res.output}"
            outputs[" ".join(args[:2])] = outputs.get(" ".join(args[:2]), "") + res.output
    return outputs


def test_few_labels_tutorial_commands(tmp_path, monkeypatch):
    pytest.importorskip("sleap_io")
    mod = _own_data()
    own = mod.DOC.read_text(encoding="utf-8")
    for old, new in mod.SUBSTITUTIONS.items():
        own = own.replace(old, new)
    text = PAGE.read_text(encoding="utf-8")
    for old in SUBSTITUTIONS:
        assert old in text, f"{PAGE.name} no longer holds {old!r}: update the test"
    for old, new in SUBSTITUTIONS.items():
        text = text.replace(old, new)
    monkeypatch.chdir(tmp_path)
    runner = CliRunner()
    # the own-rig page up to its step 7 (the tutorial's starting point)
    _run_page(own.split("## 8.")[0], runner)
    # the rig's calibration beside the session's videos, as the tutorial asks
    Path("rec/mouse1/calibration.toml").write_text(Path("calibration.toml").read_text())
    outputs = _run_page(text, runner)
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
