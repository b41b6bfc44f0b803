"""Every command of ``docs/own-data.md``, run in order on its small synthetic own rig.

The fenced ``bash`` blocks of the document are run as written (``freipose ...`` lines,
backslash continuations joined, globs expanded in the working folder) after the
substitutions below, which only shrink sizes (frames, training steps, the tiny network);
a ``toml`` block after ``<!-- file: NAME -->`` is written to NAME. Each substitution must
match the document, so the test follows it when it changes.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.io.labels import read_labels_h5
from freipose.nn.checkpoint import read_checkpoint
from freipose.testing import fenced_blocks, freipose_commands

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "own-data.md"

SUBSTITUTIONS = {
    "--frames 600": "--frames 40",
    "--gap 30": "--gap 3",
    'preset = "small"': 'preset = "tiny"',
    "steps = 600": "steps = 2",
    "checkpoint_every = 200": "checkpoint_every = 2",
    "eval_every = 200": "eval_every = 2",
    "steps = 300": "steps = 2\ninput_size = 64\nwidth = 0.25\nbatch_size = 2",
    "--n 20": "--n 3",
}


def test_own_datafreipose_commands(tmp_path, monkeypatch):
    pytest.importorskip("sleap_io")
    text = DOC.read_text(encoding="utf-8")
    for old in SUBSTITUTIONS:
        assert old in text, f"docs/own-data.md no longer holds {old!r}: update the test"
    for old, new in SUBSTITUTIONS.items():
        text = text.replace(old, new)
    monkeypatch.chdir(tmp_path)
    runner = CliRunner()
    outputs = {}
    ran = 0
    for lang, body, name in fenced_blocks(text):
        if lang == "toml" and name:
            Path(name).write_text(body, encoding="utf-8")
        if lang != "bash":
            continue
        for args in freipose_commands(body):
            res = runner.invoke(cli, args)
            assert res.exit_code == 0, f"freipose {' '.join(args)}\n{res.output}"
            outputs[" ".join(args[:2])] = outputs.get(" ".join(args[:2]), "") + res.output
            ran += 1
    assert ran >= 14
    calib = next(out for cmd, out in outputs.items() if cmd.startswith("calib rec/"))
    assert "WARNING" not in calib, calib  # the documented recording covers the floor
    lab = read_labels_h5("labels/all.h5")
    info = lab.sessions["mouse1"]
    assert info.instances == "predicted" and info.fps == 30.0
    assert len(read_labels_h5("labels/eval.h5")) == 10  # a quarter of 40 instants
    cfg = read_checkpoint("runs/pose/model.pt")["config"]["model"]
    base = read_checkpoint("runs/baseline/model.pt")["config"]["model"]
    assert cfg["cube_size"] == base["cube_size"] < 320  # sized for the mouse, the same for both
    assert re.search(r"cube \d+ mm from the training labels", outputs["train train.toml"])
    assert "reference, median pose at held-out centre" in outputs["eval runs/pose/model.pt"]
    # without --detector or --fixed-boxes, predict says which boxes it uses and why
    assert "using background subtraction: no detector given" in outputs["predict rec/mouse1"]
    for poses in ("poses", "poses_fixed", "poses_detector"):
        assert Path(poses, "mouse1.poses.h5").is_file()
    # every synthetic frame is labeled, so none is left to propose: the header only
    assert Path("next_frames.csv").read_text().startswith("session,frame_index")
