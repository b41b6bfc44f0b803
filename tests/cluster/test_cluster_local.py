"""Units on the local executor: the plan, the joined files against a direct run, a unit
that fails and is retried, a report of what failed and ``freipose jobs --resume``."""

from __future__ import annotations

import builtins

import pytest
from click.testing import CliRunner
from conftest import SESSIONS, cluster_file, predict_args
from predict_helpers import h5_equal

from freipose.cli.main import cli
from freipose.cluster.config import ClusterConfig, ClusterConfigError, read_cluster_config
from freipose.cluster.executors import ExecutorError, SlurmExecutor
from freipose.cluster.predict import PredictTask, plan_units
from freipose.io.lock import output_lock
from freipose.io.session import discover_sessions


def _run(args):
    return CliRunner().invoke(cli, args)


def test_config_checks_values_and_keys(tmp_path):
    with pytest.raises(ClusterConfigError, match="executor must be one of local, slurm"):
        ClusterConfig(executor="pbs")
    with pytest.raises(ClusterConfigError, match="chunk_frames must be a whole number >= 1"):
        ClusterConfig(chunk_frames=0)
    with pytest.raises(ClusterConfigError, match="mem_gb must be > 0"):
        ClusterConfig(mem_gb=float("nan"))
    path = cluster_file(tmp_path, executor="slurm", partiton="gpu")
    with pytest.raises(ClusterConfigError, match="unknown key 'partiton'.*partition"):
        read_cluster_config(path)
    cfg = read_cluster_config(cluster_file(tmp_path, executor="slurm", cpus=4), cpus=None,
                              chunk_frames=100)  # fmt: skip
    assert (cfg.executor, cfg.cpus, cfg.chunk_frames) == ("slurm", 4, 100)


def test_units_are_whole_batches_of_the_session(toy_study):
    found = discover_sessions(toy_study["sessions"][:1])

    def units(chunk, batch, frames=None):
        task = PredictTask(tuple(found), toy_study["model"], None, toy_study["root"], frames,
                           batch, "cpu", True, None, chunk, 1)  # fmt: skip
        return [(u.index, u.count, u.frames) for u in plan_units(task)]

    assert units(8, 4) == [(i, 5, 8) for i in range(5)]
    assert units(10, 4) == [(0, 4, 12), (1, 4, 12), (2, 4, 12), (3, 4, 4)]  # whole batches
    assert units(1000, 4) == [(0, 1, 40)]
    assert units(8, 4, "5:25") == [(0, 3, 8), (1, 3, 8), (2, 3, 4)]


def test_local_units_equal_a_direct_run_and_rerun_submits_nothing(toy_study, tmp_path):
    out = tmp_path / "poses"
    cfg = cluster_file(tmp_path, executor="local", chunk_frames=8, array_parallelism=2, poll_s=0.2)
    res = _run(predict_args(toy_study, out, "--cluster", str(cfg)))
    assert res.exit_code == 0, res.output
    assert "15 units done (15 jobs submitted in this run)" in res.output
    for s in SESSIONS:
        assert h5_equal(toy_study["direct"] / f"{s}.poses.h5", out / f"{s}.poses.h5") == []
    assert sorted(p.name for p in out.glob("*.h5")) == [f"{s}.poses.h5" for s in SESSIONS]
    status = _run(["jobs", str(out)])
    assert status.exit_code == 0, status.output
    assert all(f"{s}: 5 done" in status.output for s in SESSIONS)
    again = _run(predict_args(toy_study, out, "--cluster", str(cfg)))
    assert again.exit_code == 0, again.output
    assert "(0 jobs submitted in this run)" in again.output


def test_failing_unit_is_retried_reported_and_resumed(toy_study, tmp_path):
    out = tmp_path / "poses"
    cfg = cluster_file(tmp_path, executor="local", chunk_frames=8, array_parallelism=2,
                       poll_s=0.2, max_retries=1)  # fmt: skip
    blocked = out / "s1.shard-2-of-5.poses.h5"
    out.mkdir()
    with output_lock(blocked, "poses file"):  # this live process holds it: the unit fails
        res = _run(predict_args(toy_study, out, "--cluster", str(cfg)))
        assert res.exit_code != 0
        assert "1 of 15 units failed" in res.output
        assert "s1.2-of-5: OutputLockedError" in res.output and "after 2 jobs" in res.output
        assert f"freipose jobs {out} --resume" in res.output
        assert (out / "s0.poses.h5").is_file() and (out / "s2.poses.h5").is_file()
        assert not (out / "s1.poses.h5").exists()  # never a session with a missing unit
        status = _run(["jobs", str(out)])
        assert "s1: 4 done, 1 failed" in status.output, status.output
        assert "s1.2-of-5: failed, job local-" in status.output
    resumed = _run(["jobs", str(out), "--resume"])
    assert resumed.exit_code == 0, resumed.output
    assert "s1: 5 done" in resumed.output
    for s in SESSIONS:
        assert h5_equal(toy_study["direct"] / f"{s}.poses.h5", out / f"{s}.poses.h5") == []


def test_options_that_do_not_go_together(toy_study, tmp_path):
    res = _run(predict_args(toy_study, tmp_path / "a", "--executor", "local", "--shard", "0/2"))
    assert res.exit_code != 0 and "--shard is what --executor does" in res.output
    res = _run(predict_args(toy_study, tmp_path / "b", "--chunk-frames", "8"))
    assert res.exit_code != 0 and "add --executor" in res.output
    res = _run(["jobs", str(tmp_path)])
    assert res.exit_code != 0 and "no job found" in res.output


def test_slurm_executor_without_submitit_says_what_to_install(monkeypatch, tmp_path):
    real_import = builtins.__import__

    def no_submitit(name, *args, **kwargs):
        if name == "submitit":
            raise ImportError("No module named 'submitit'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_submitit)
    with pytest.raises(ExecutorError, match=r'pip install "freipose\[cluster\]"'):
        SlurmExecutor(ClusterConfig(executor="slurm"), tmp_path)
