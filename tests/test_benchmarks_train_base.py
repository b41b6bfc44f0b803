"""benchmarks/train_base.py: the base models' training sessions and command line."""

from __future__ import annotations

import json
from collections import Counter
from types import SimpleNamespace

import pytest

BENCHMARK = "train_base"  # the script the conftest fixture ``bench`` loads


def _stim(bench, index: int):
    return bench.scene_config(bench.SEED_START + index, index, 100, 5.0).stimulation


def test_the_first_sessions_stimulate_every_other_one_in_turn(bench):
    firsts = [_stim(bench, i) for i in range(bench.FIRST_MOVING)]
    assert all(s is None for s in firsts[0::2])
    moved = [(s.body_part, s.effect) for s in firsts[1::2]]
    assert moved[:3] == [
        ("Paw Front Right", "oscillate"),
        ("Paw Front Left", "lift"),
        ("Paw Back Right", "freeze"),
    ]


def test_later_sessions_mostly_move_a_paw_and_are_fixed_by_their_seed(bench):
    later = range(bench.FIRST_MOVING, bench.FIRST_MOVING + 64)
    stims = [_stim(bench, i) for i in later]
    assert [s is None for s in stims] == [i % 4 == 0 for i in later]
    parts = Counter(s.body_part for s in stims if s is not None)
    assert set(parts) <= set(bench.MOVED_PARTS)
    front = parts["Paw Front Right"] + parts["Paw Front Left"]
    assert front > sum(parts.values()) / 3
    moving = sum(s.effect in ("oscillate", "lift") for s in stims if s is not None)
    assert moving >= 0.75 * sum(parts.values())
    assert stims == [_stim(bench, i) for i in later]


def test_held_out_sessions_are_not_training_sessions(bench):
    args = bench._parser().parse_args(["--sessions", "48"])
    assert bench.SEED_START + args.sessions - 1 < bench.HELD_OUT_SEED_START


def test_unknown_network_names_are_refused(bench, tmp_path):
    with pytest.raises(SystemExit, match="--networks"):
        bench.main(["--work", str(tmp_path), "--networks", "voxel,unet", "--export-only"])


def _fake_export(bench, folder, monkeypatch, shipped, steps, export_only):
    """``export_all`` on ``folder`` holding ``shipped`` as its manifest, without networks.

    ``steps`` maps a network to its run's step (read when exporting, so it may change).
    Returns a function ``export(jobs, command, trained)`` and the manifest's path.
    """
    (folder / "bases.json").write_text(json.dumps({"bases": shipped}))
    args = SimpleNamespace(export=folder, export_only=export_only, warm_start=True)
    trainer = SimpleNamespace(
        args=args, work=folder / "run", run_dir=lambda n: folder / n, shipped=lambda n: n
    )
    monkeypatch.setattr(bench, "current_step", lambda t, job: steps[job.name])
    monkeypatch.setattr(bench, "_export_one", lambda t, job, dest: steps[job.name])
    monkeypatch.setattr(bench, "_validation_rows", lambda path: [])
    monkeypatch.setattr(
        bench,
        "_provenance",
        lambda t, job, dest, step, command: {
            "steps": step,
            "command": command,
            "work": str(t.work),
        },
    )

    def export(jobs, command, trained):
        bench.export_all(trainer, jobs, command, evaluate=False, trained=trained)

    return export, folder / "bases.json"


def test_export_keeps_untrained_bases_and_records_a_warm_start_once(bench, tmp_path, monkeypatch):
    shipped = [
        {"name": "voxel", "steps": 5000, "command": "first", "work": "old", "held_out": {}},
        {"name": "baseline", "steps": 4000, "command": "first", "work": "old", "held_out": {}},
    ]
    steps = {"voxel": 200, "baseline": 7}
    export, manifest = _fake_export(bench, tmp_path, monkeypatch, shipped, steps, False)
    jobs = [bench.Job("voxel", 8000, 0.5), bench.Job("baseline", 3000, 0.25)]
    for step in (200, 400):  # two chunks of the same warm-started run
        steps["voxel"] = step
        export(jobs, "second", trained={"voxel"})
        voxel, baseline = json.loads(manifest.read_text())["bases"]
        assert baseline == shipped[1]
        assert voxel["steps"] == step and voxel["command"] == "second"
        assert voxel["started_from"] == {"steps": 5000, "command": "first", "held_out": {}}


def test_an_export_only_run_records_no_warm_start(bench, tmp_path, monkeypatch):
    shipped = [{"name": "voxel", "steps": 5000, "command": "first", "work": "old"}]
    export, manifest = _fake_export(bench, tmp_path, monkeypatch, shipped, {"voxel": 5000}, True)
    export([bench.Job("voxel", 5000, 1.0)], "again", trained={"voxel"})
    (voxel,) = json.loads(manifest.read_text())["bases"]
    assert "started_from" not in voxel
    assert voxel["command"] == "first"  # an --export-only run keeps the training command
