"""Every command of ``docs/own-data.md``, run in order on its small synthetic own rig.

The commands run once per test session (``own_data_run`` in ``conftest.py``, with the
substitutions of ``doc_pages.py``, which only shrink sizes); this test checks what
they printed and wrote.
"""

from __future__ import annotations

import re
from pathlib import Path

from freipose.io.labels import read_labels_h5
from freipose.nn.checkpoint import read_checkpoint


def test_own_datafreipose_commands(own_data_run, monkeypatch):
    outputs, ran = own_data_run["outputs"], own_data_run["ran"]
    monkeypatch.chdir(own_data_run["folder"])
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
