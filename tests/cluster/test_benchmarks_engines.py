"""``benchmarks/engines.py``: its figures, table and messages, and (on SLURM) a timed run."""

from __future__ import annotations

import argparse
import importlib.util
import operator
import socket
import sys

import pytest
from conftest import slurm_reason

BENCHMARK = "engines"  # the script the conftest fixture ``bench`` loads


def test_a_missing_engine_is_named_with_what_to_install(bench, monkeypatch):
    # dask and distributed installed, dask-jobqueue not
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name: None if name == "dask_jobqueue" else object())  # fmt: skip
    said = bench.missing(["dask"])
    assert list(said) == ["dask"]
    assert "dask_jobqueue not installed" in said["dask"]
    assert "pip install dask distributed dask-jobqueue" in said["dask"]
    assert "distributed," not in said["dask"]  # only the absent module is named


def test_without_any_engine_the_script_stops_and_says_what_to_install(bench, monkeypatch, capsys):
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    monkeypatch.setattr(bench, "slurm_problem", lambda: None)
    monkeypatch.setattr(sys, "argv", ["engines.py"])
    with pytest.raises(SystemExit, match="no engine to measure"):
        bench.main()
    err = capsys.readouterr().err
    assert 'submitit skipped: submitit not installed; pip install "freipose[cluster]"' in err
    assert "dask skipped: dask, distributed, dask_jobqueue not installed" in err


def test_overhead_per_unit_counts_waves_of_the_slots(bench):
    # 8 units of 2 s on 2 slots: 4 waves, 8 s of work
    assert bench.overhead_per_unit(10.0, 8, 2, 2.0) == pytest.approx(0.5)
    # 7 units still take 4 waves on 2 slots
    assert bench.overhead_per_unit(9.0, 7, 2, 2.0) == pytest.approx(0.25)
    assert bench.medians({"a": [3.0, 1.0, 2.0], "b": []}) == {"a": 2.0}


def test_the_table_shows_each_run_the_cancellations_and_ray(bench):
    figures = {
        "medians": {"submitit_trivial_s": 8.0, "submitit_sleep_s": 13.5,
                    "dask_cold_trivial_s": 2.7, "dask_cold_sleep_s": 10.1},
        "submitit_overhead_per_unit_s": 1.375, "submitit_speedup_vs_serial_sleep": 1.19,
        "dask_cold_overhead_per_unit_s": 0.53, "dask_cold_speedup_vs_serial_sleep": 1.58,
        "submitit_measured_needs": {"listening_ports": 0},
        "dask_measured_needs": {"listening_ports": 4},
        "cancel": {
            "submitit": {"outcome": "no answer", "seconds_to_answer": None, "starts": 1,
                         "squeue_gone_s": 5.1},
            "dask": {"outcome": "result", "seconds_to_answer": 17.8, "starts": 2,
                     "worker_jobs_after": 1},
        },
        "preempt_submitit": {"outcome": "result", "seconds_to_answer": 130.0, "starts": 2,
                             "state_5s_after": "PENDING (BeginTime)"},
        "skipped": {},
    }  # fmt: skip
    text = bench.table(figures)
    rows = {line.split()[0]: line.split() for line in text.splitlines()[1:3]}
    assert rows["submitit"][1:6] == ["8.00", "13.50", "1.38", "1.19", "0"]
    assert rows["dask_cold"][1:6] == ["2.70", "10.10", "0.53", "1.58", "4"]
    assert "submitit: scancel midway: no answer (the timeout); the unit started 1x; " \
           "squeue dropped the job after 5.1 s" in text  # fmt: skip
    assert "dask: scancel midway: result after 17.8 s; the unit started 2x; worker jobs left: 1" \
        in text  # fmt: skip
    assert "result after 130.0 s, started 2x; 5 s after: PENDING (BeginTime)" in text
    assert text.splitlines()[-1].startswith("ray") and "ray start --head" in text


def test_listening_ports_counts_this_process_s_listening_sockets(bench):
    before = bench.listening_ports()
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        assert bench.listening_ports() == before + 1
    assert bench.listening_ports() == before


def test_a_unit_notes_each_start_with_its_slurm_job(bench, tmp_path, monkeypatch):
    monkeypatch.setenv("SLURM_JOB_ID", "41")
    monkeypatch.delenv("SLURM_ARRAY_TASK_ID", raising=False)
    assert bench.marked_nap((str(tmp_path), "u0", 0.0)) == "u0"
    monkeypatch.setenv("SLURM_JOB_ID", "57")
    monkeypatch.setenv("SLURM_ARRAY_JOB_ID", "50")
    monkeypatch.setenv("SLURM_ARRAY_TASK_ID", "7")
    bench.marked_nap((str(tmp_path), "u0", 0.0))
    assert bench.starts(tmp_path, "u0") == ["41", "50_7"]
    assert bench.starts(tmp_path, "u1") == []


@pytest.mark.slurm
def test_submitit_runs_units_on_slurm_and_listens_on_no_port(bench, tmp_path):
    reason = slurm_reason()
    if reason:
        pytest.skip(reason)
    args = argparse.Namespace(partition="debug", parallelism=2, timeout=120.0)
    res = bench.time_submitit(operator.neg, [1, 2], tmp_path, args)
    assert res["results"] == [-1, -2]
    assert res["listening_ports"] == 0
    assert res["files_per_unit"] >= 3  # the pickled call, the logs and the result
    assert res["seconds"] > 0
