"""``benchmarks/accuracy.py``: every session on a lab's own rig and coat, a base snapshot."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from freipose._compat import tomllib
from freipose.nn.checkpoint import read_checkpoint

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "freipose" / "models"


BENCHMARK = "accuracy"  # the script the conftest fixture ``bench`` loads


def test_rig_and_coat_of_every_session_and_a_base_snapshot(bench, tmp_path, capsys):
    if not (MODELS / "voxel_small.pt").is_file():
        pytest.skip("no voxel base is shipped in freipose/models")
    snapshot = tmp_path / "bases"
    snapshot.mkdir()
    for name in ("bases.json", "voxel_small.pt"):
        shutil.copy(MODELS / name, snapshot / name)
    out = tmp_path / "acc"
    args = ["--out", str(out), "--steps", "2", "--train-sessions", "1", "--frames", "3"]
    args += ["--eval-frames", "2", "--size", "96", "80", "--kinds", "voxel"]
    args += ["--init", "base,scratch", "--base-dir", str(snapshot)]
    args += ["--rig-layout", "arc", "--rig-cameras", "3", "--appearance", "piebald"]
    assert bench.main(args) == 0
    scenes = sorted((out / "data").glob("*/scene.toml"))
    assert [p.parent.name.split("_")[0] for p in scenes] == ["eval", "train0"]
    for path in scenes:  # training AND held-out sessions on the rig and coat given
        scene = tomllib.loads(path.read_text())["scene"]
        assert (scene["layout"], scene["appearance"], scene["n_cameras"]) == (
            "arc",
            "piebald",
            3,
        )
    base = read_checkpoint(out / "base" / "main" / "voxel" / "model.pt")
    scratch = read_checkpoint(out / "main" / "voxel" / "model.pt")
    assert base["config"]["model"]["init"] == str(snapshot / "voxel_small.pt")
    assert scratch["config"]["model"]["init"] == "scratch"
    assert "INIT (main experiment, equal budget)" in capsys.readouterr().out
    assert set(json.loads((out / "results.json").read_text())["init"]) == {"base", "scratch"}


def test_wrong_settings_fail_before_any_output(bench, tmp_path):
    out = tmp_path / "acc"
    with pytest.raises(SystemExit):
        bench.main(["--out", str(out), "--rig-layout", "circle"])
    with pytest.raises(SystemExit, match="bases.json"):
        bench.main(["--out", str(out), "--init", "base", "--base-dir", str(tmp_path)])
    assert not out.exists()
