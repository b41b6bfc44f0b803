"""Every command of the tutorials that build on the demo, run on the tiny demo's folder.

``docs/tutorials/demo.md``, ``analysis.md`` and ``cluster.md`` start from a finished
``freipose demo`` folder; the tests copy the tiny demo that the other demo tests share
(``tiny_demo`` in ``conftest.py``) to ``freipose_demo/`` and run the fenced ``bash`` blocks
of each page as written (``freipose ...`` lines, backslash continuations joined, globs
expanded), after the substitutions below, which adapt them to the tiny preset. A ``toml``
block after ``<!-- file: NAME -->`` is written to NAME. Each substitution must match the
page, so the test follows it when it changes. ``tests/test_own_data.py`` does the same for
``docs/own-data.md``.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import h5py
import pandas as pd
import pytest
from click.testing import CliRunner
from doc_pages import run_blocks, substituted

ROOT = Path(__file__).resolve().parents[2]
TUTORIALS = ROOT / "docs" / "tutorials"

#: the demo page runs the demo on the tiny preset (the copied folder is complete, so the
#: run only checks its markers and rewrites the summary)
DEMO_SUBSTITUTIONS = {"\nfreipose demo\n": "\nfreipose demo --preset tiny\n"}

#: the tiny demo's protocol (one 0.8 s window in 2.4 s) and its detector (4 training
#: steps, which the tiny demo does not use either: it predicts with background subtraction)
ANALYSIS_SUBSTITUTIONS = {
    "--detector freipose_demo/train/detector/detector.pt": "--method bgsub",
    "--stft-window 32": "--stft-window 16",
    "--onset-delay 0.6": "--onset-delay 0.2",
    "--margin 0.5": "--margin 0.3",
    "--pre 1 --post 1": "--pre 0.5 --post 0.5",
}


#: the tiny demo's sessions (60 frames: 2 units of at most 32) on the local executor, without a GPU
CLUSTER_SUBSTITUTIONS = {
    "--detector freipose_demo/train/detector/detector.pt": "--method bgsub",
    "--chunk-frames 250": "--chunk-frames 30",
    'executor = "slurm"': 'executor = "local"',
    "gpus = 1 ": "gpus = 0 ",
    "cpus = 4 ": "cpus = 1 ",
    "array_parallelism = 32": "array_parallelism = 2",
    "chunk_frames = 6000": "chunk_frames = 30",
    "--device cuda": "--device cpu",
}


def run_page(name: str, substitutions: dict[str, str]) -> dict[str, str]:
    """Run the page's blocks in the current folder; the output of each command by its line."""
    outputs, _ = run_blocks(substituted(TUTORIALS / name, substitutions), CliRunner(), None)
    return outputs


@pytest.fixture
def demo_folder(tiny_demo, tmp_path, monkeypatch):
    """A working folder holding a copy of the tiny demo as ``freipose_demo/``."""
    shutil.copytree(tiny_demo[0], tmp_path / "freipose_demo")
    monkeypatch.chdir(tmp_path)
    return tmp_path


@pytest.mark.slow
def test_demo_tutorialfreipose_commands(demo_folder):
    out = run_page("demo.md", DEMO_SUBSTITUTIONS)
    assert len(out) == 4
    # the rerun skipped the seven finished steps and wrote the report again
    rerun = out["demo --preset tiny"]
    assert rerun.count("done earlier") == 7 and "open freipose_demo/report.html" in rerun
    assert "cam6" in out["calib show freipose_demo/calibration/calibration.toml"]
    assert Path("demo_eval/metrics.json").is_file()
    table = pd.read_csv("rat1_day2.csv")
    assert {"frame", "time_s", "Nose_x_mm", "Nose_confidence"} <= set(table.columns)
    assert len(table) == 60  # the tiny preset's frames


@pytest.mark.slow
def test_analysis_tutorialfreipose_commands(demo_folder):
    run_page("analysis.md", ANALYSIS_SUBSTITUTIONS)
    assert Path("rec/rat1_day4/events.csv").read_text().startswith("start_s,end_s")
    classification = pd.read_csv("results/classification.csv")
    assert classification["evaluated_on"].tolist() == ["rat1"]
    # both test days are scored: day 2 and the new day 4, 60 frames each before labelling
    assert 60 < classification["n_frames"].iloc[0] <= 120
    attribution = pd.read_csv("results/attribution.csv")
    assert attribution["rank"].tolist() == list(range(1, len(attribution) + 1))
    assert Path("results/attribution_rat1_paw.png").is_file()
    with h5py.File("rat1_day4.vars.h5", "r") as f:
        assert f["values"].shape == (60, 336)  # 12 rat keypoints, 9 STFT frequencies
        assert f.attrs["floor_source"] == "floor.toml"


@pytest.mark.slow
def test_cluster_tutorialfreipose_commands(demo_folder):
    out = run_page("cluster.md", CLUSTER_SUBSTITUTIONS)
    for folder in ("poses_units", "poses_cluster"):
        for day in ("rat1_day2", "rat1_day3"):
            with h5py.File(f"{folder}/{day}.poses.h5", "r") as f:
                assert f["poses"].shape[0] == 60 and bool(f.attrs["complete"])
        assert not list(Path(folder).glob("*.shard-*"))
    status = out["jobs poses_units"]
    assert "rat1_day2: 2 done" in status and "rat1_day3: 2 done" in status
