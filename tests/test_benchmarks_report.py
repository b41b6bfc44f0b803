"""``benchmarks/report.py``: docs/benchmarks.md and the README's demo table from result files."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCHMARK = "report"  # the script the conftest fixture ``bench`` loads


def test_the_committed_page_and_readme_block_are_up_to_date(bench, capsys):
    # a stale page (a result recorded or removed without regenerating) fails here
    code = bench.main(["--check"])
    assert code == 0, capsys.readouterr().err + " (run: python benchmarks/report.py)"


def _result(mp, name: str, figures: dict, kind: str, seed: int, **extra) -> Path:
    """Record a result as ``write_result`` does, on a pretend machine of CPU kind ``kind``."""
    import _results

    mp.setattr(_results, "machine", lambda: {
        "platform": "Linux", "cpu_model": f"CPU {kind}", "cores": 2, "memory_gib": 8.0,
        "cpu_flags": [], "cpu_kind": kind, "host_hash": kind[:6],
    })  # fmt: skip
    return _results.write_result(name, figures, command=["benchmarks/x.py", "--seed", str(seed)],
                                 extra={"seed": seed, **extra})  # fmt: skip


@pytest.fixture
def fake_results(bench, tmp_path, monkeypatch):
    folder = tmp_path / "results"
    monkeypatch.setenv("FREIPOSE_RESULTS_DIR", str(folder))
    mp = monkeypatch
    # the demo as it runs today: the default preset's starting weights and schedule
    from freipose.demo.presets import PRESETS

    now = dict(preset="small", init=PRESETS["small"].init,
               schedule=bench.schedule_of(PRESETS["small"].pose))  # fmt: skip
    for seed, (jpe, best) in enumerate([(3.6, "v1"), (3.9, "v1"), (3.7, "v2")]):
        figs = {"held_out_jpe_mm": {"voxel_P1": jpe}, "analysis": {"predicted": {
            "best_variable": best, "balanced_accuracy": 0.7 + seed / 100},
            "smoothed": {"balanced_accuracy": 0.8 if seed == 0 else 0.6}}}  # fmt: skip
        _result(mp, "demo", figs, "avx512", seed, **now)
    _result(mp, "demo", {"held_out_jpe_mm": {"voxel_P1": 4.2}}, "avx2", 0, **now)
    _result(mp, "demo", {"held_out_jpe_mm": {"voxel_P1": 99.0}}, "avx2", 0, preset="tiny")
    # a run of another schedule: its own table on the page, not in the README's ranges
    earlier = {**now, "schedule": {**now["schedule"], "steps": 1}}
    _result(mp, "demo", {"held_out_jpe_mm": {"voxel_P1": 77.0}}, "avx512", 0, **earlier)
    _result(mp, "synth", {"render_fps": 10.0, "ok": True}, "avx2", 0, frames=100)
    _result(mp, "synth", {"render_fps": 30.0, "ok": True}, "avx2", 0, frames=20)
    return folder


def test_files_name_the_date_commit_and_cpu_kind_and_hold_the_provenance(fake_results):
    files = sorted((fake_results / "demo").glob("*.json"))
    assert len(files) == 6
    date, commit, machine, n = files[0].stem.split("_")
    assert len(date) == 10 and machine.startswith(("avx512-", "avx2-")) and int(n) >= 1
    rec = json.loads(files[0].read_text())
    assert rec["benchmark"] == "demo" and rec["extra"]["seed"] in (0, 1, 2)
    assert {"machine", "versions", "git", "date", "command", "figures"} <= set(rec)
    assert rec["versions"]["python"] and "dirty" in rec["git"]


def test_aggregation_gives_median_range_runs_and_seeds(bench, fake_results):
    records = bench.load_results(folder=fake_results)
    text = bench.page(records)
    # 3 avx512 runs and 1 avx2 run of the default preset: a column per kind
    assert "| held_out_jpe_mm/voxel_P1 | 3.8 (3.6-4.2) | 3.7 (3.6-3.9) | 4.2 |" in text
    assert "- runs: 4 (seeds 0, 1, 2); CPU kinds: avx512 3, avx2 1" in text
    assert "| analysis/predicted/best_variable | v1 (2x), v2 | v1 (2x), v2 | - |" in text
    # other settings (the tiny preset, other frame counts) are other tables, not in the range
    assert text.count("## demo") == 1 and "### preset=tiny" in text and "99" in text
    assert "77" in text and text.count("### ") == 5  # the demo's 3 settings, synth's 2
    assert "### frames=100" in text and "### frames=20" in text
    assert "| render_fps | 10 |" in text and "| ok | true |" in text
    assert "```bash\npython benchmarks/x.py --seed " in text


def test_every_benchmark_script_has_a_section(bench, tmp_path):
    # the scripts; modules named _* are their shared helpers
    scripts = {p.stem for p in (ROOT / "benchmarks").glob("*.py") if not p.stem.startswith("_")}
    scripts -= {"report"}
    assert set(bench.BENCHMARKS) == scripts
    for name in scripts:  # each records its figures
        text = (ROOT / "benchmarks" / f"{name}.py").read_text()
        assert re.search(rf'write_result\(\s*"{name}"', text), name
    text = bench.page([])
    assert all(f"## {name}\n\nNo run is recorded yet" in text for name in scripts)


def test_readme_block_shows_ranges_per_cpu_kind(bench, fake_results, tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{bench.BEGIN}\nold\n{bench.END}\nrest\n")
    page = tmp_path / "benchmarks.md"
    args = ["--results", str(fake_results), "--page", str(page), "--readme", str(readme),
            "--tutorial", str(tmp_path / "cluster.md")]  # fmt: skip
    assert bench.main([*args, "--check"]) == 1
    assert bench.main(args) == 0
    text = readme.read_text()
    assert text.startswith("intro\n") and text.endswith(f"{bench.END}\nrest\n")
    assert "old" not in text
    assert "| figure | avx512: 3 runs, seeds 0, 1, 2 | avx2: 1 run, seed 0 |" in text
    assert "| Held-out median JPE, voxel network (P1) | 3.6-3.9 mm | 4.2 mm |" in text
    assert "77" not in text and "99" not in text  # other schedules and presets
    assert "v1 (2 of 4), v2 (1 of 4)" in text
    # a conclusion that does not hold in every run says so
    assert "Smoothing raised the balanced accuracy in 1 of 3 runs" in text
    assert bench.main([*args, "--check"]) == 0


def test_a_readme_without_markers_is_left_alone(bench, fake_results, tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text("no markers\n")
    args = ["--results", str(fake_results), "--page", str(tmp_path / "b.md"),
            "--tutorial", str(tmp_path / "cluster.md")]  # fmt: skip
    assert bench.main([*args, "--readme", str(readme)]) == 0
    assert readme.read_text() == "no markers\n"


def test_cluster_tutorial_block_reads_the_latest_run(bench, monkeypatch, tmp_path):
    monkeypatch.setenv("FREIPOSE_RESULTS_DIR", str(tmp_path / "results"))
    fps = {"direct": 4.0, "local": 3.8, "slurm": 3.6}
    paper = {"frames": 360e6, "core_s_per_frame_7cams": 0.875, "units": 60000.0,
             "overhead_share": 0.001, "core_hours": 87500.0, "wall_hours_on_100_workers": 875.0,
             "wall_hours_on_1000_workers": 87.5}  # fmt: skip
    figures = {"frames_per_s": fps, "found_share": 0.99, "ratio_local_to_direct": 0.95,
               "ratio_slurm_to_direct": 0.9, "overhead_s_local": 2.0, "overhead_s_slurm": 5.0,
               "identical_local_slurm": True, "identical_to_one_thread_direct_local": True,
               "identical_to_one_thread_direct_slurm": True, "paper_1000h_7cams": paper,
               "load_average_1min": {"start": 1.0, "end": 2.0},
               "unit_s_per_frame_slurm": 0.1}  # fmt: skip
    _result(monkeypatch, "cluster", figures, "avx2", 0, sessions=8, frames=150, cameras=4,
            chunk_frames=150, cores=2)  # fmt: skip
    doc = tmp_path / "cluster.md"
    doc.write_text(f"intro\n{bench.CLUSTER_BEGIN}\nold\n{bench.CLUSTER_END}\nrest\n")
    args = ["--results", str(tmp_path / "results"), "--page", str(tmp_path / "b.md"),
            "--readme", str(tmp_path / "none.md"), "--tutorial", str(doc)]  # fmt: skip
    assert bench.main(args) == 0
    text = doc.read_text()
    assert text.startswith("intro\n") and text.endswith(f"{bench.CLUSTER_END}\nrest\n")
    assert "| SLURM: 2 one-core array tasks | 3.6 | 0.90 | 5 s |" in text
    assert "0.88 core-seconds per 7-camera frame" in text and "87500 core-hours" in text
    assert "875 hours on 100 one-core workers" in text and "+ 60000 · 5 / N" in text
    assert "A unit of 150 frames did 15 s of work after 5 s of overhead (25 % of its" in text
    assert "a SLURM unit's cost per frame after its first batch" in text
    assert "The units ran faster" not in text
    assert " on 20" not in text  # the run's date is on the benchmarks page, not in the prose
    assert bench.main([*args, "--check"]) == 0


def test_results_off_writes_nothing(bench, monkeypatch, tmp_path):
    from _results import write_result

    monkeypatch.setenv("FREIPOSE_RESULTS_DIR", "off")
    assert write_result("x", {"a": 1.0}) is None
    monkeypatch.setenv("FREIPOSE_RESULTS_DIR", str(tmp_path))
    path = write_result("x", {"a": float("nan")})
    assert json.loads(path.read_text())["figures"] == {"a": None}
    assert write_result("x", {"a": 2.0}).name.endswith("_2.json")


def test_commands_are_shown_from_the_repository_root_without_local_folders(bench):
    rec = {"command": ["cluster.py", "--sessions", "8", "--work", "/tmp/cb/run1",
                       "--out=/work/runs/x", "--demo", "/work/runs/demo-seed0",
                       "--workdir", "/tmp/s"]}  # fmt: skip
    assert bench.command_text(rec) == (
        "python benchmarks/cluster.py --sessions 8 --work WORK --out=OUT --demo DEMO"
        " --workdir WORKDIR"
    )
    rec = {"command": ["benchmarks/predict.py", "--model", "/m/voxel_small.pt"]}
    assert bench.command_text(rec) == "python benchmarks/predict.py --model /m/voxel_small.pt"
    assert bench._setting("/work/main/freipose/models/voxel_small.pt") == "voxel_small.pt"
    assert bench._setting("small") == "small" and bench._setting(3) == 3
    # a text figure that is a path on the recording machine: its file name
    cell = bench.cell(bench.spread(["/work/runs/demo-seed0/analysis/study.toml"]))
    assert cell == "study.toml"
