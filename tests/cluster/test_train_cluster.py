"""``freipose train --executor local``: two gloo processes as a job, resumed bit for bit.

The job's run equals two processes launched directly (the way ``torchrun`` does) that
were stopped after a checkpoint and continued by the job; a second run of the command
reports the run complete; ``freipose jobs RUN`` shows the job; bad requests are refused
before anything is submitted.
"""

from __future__ import annotations

import socket
import sys

import pytest
import torch
from click.testing import CliRunner
from conftest import EVERY, LOCAL_JOB, STEPS, logged_steps, same_weights, train_config
from gloo_direct import direct_process

from freipose.cli.main import cli
from freipose.cluster.driver import read_journal
from freipose.nn.checkpoint import read_checkpoint

JOB = LOCAL_JOB


@pytest.mark.slow
def test_local_job_of_two_gloo_processes_continues_a_run_bit_for_bit(gloo_run, tmp_path):
    cfg, whole = gloo_run["config"], gloo_run["run"]
    assert "1 node(s) x 2 process(es) on CPUs" in gloo_run["output"]
    assert logged_steps(whole) == list(range(1, STEPS + 1))
    # two processes launched directly stop after a checkpoint; the job continues their run
    part = tmp_path / "part"
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    torch.multiprocessing.spawn(direct_process, args=(port, str(cfg), str(part), EVERY),
                                nprocs=2)  # fmt: skip
    assert read_checkpoint(part / "checkpoint.pt")["step"] == EVERY
    runner = CliRunner()
    res = runner.invoke(cli, ["-q", "train", str(cfg), "--out", str(part), *JOB])
    assert res.exit_code != 0 and "pass --resume" in res.output, res.output
    res = runner.invoke(cli, ["-q", "train", str(cfg), "--out", str(part), *JOB, "--resume"])
    assert res.exit_code == 0, res.output
    assert same_weights(whole / "model.pt", part / "model.pt")
    assert logged_steps(part) == list(range(1, STEPS + 1))
    # the same command again: complete, nothing submitted
    res = runner.invoke(cli, ["-q", "train", str(cfg), "--out", str(whole), *JOB])
    assert res.exit_code == 0 and "the run is complete" in res.output, res.output
    assert [e["event"] for e in read_journal(whole)] == ["submitted", "done"]
    res = runner.invoke(cli, ["jobs", str(whole)])
    assert res.exit_code == 0, res.output
    assert f"2 process(es)): done, step {STEPS} of {STEPS}, job local-1 (attempt 1)" in res.output


def test_a_job_that_fails_is_retried_then_reported_with_its_error(tmp_path):
    cfg = train_config(tmp_path, steps=2, checkpoint_every=2)
    (tmp_path / "data" / "labels.h5").write_bytes(b"not a labels file")
    out = tmp_path / "run"
    res = CliRunner().invoke(cli, ["-q", "train", str(cfg), "--out", str(out), "--executor",
                                   "local", "--threads", "1", "--max-retries", "1"])  # fmt: skip
    assert res.exit_code != 0
    assert "ended without model.pt after 2 jobs" in res.output, res.output
    assert "labels.h5" in res.output and "--resume" in res.output
    res = CliRunner().invoke(cli, ["jobs", str(out)])
    assert "failed, step 0 of 2, job local-2 (attempt 2)" in res.output, res.output
    assert f"finish with: freipose jobs {out} --resume" in res.output


def test_bad_requests_are_refused_before_submitting(tmp_path, monkeypatch):
    cfg = train_config(tmp_path, steps=2, checkpoint_every=2)
    out = str(tmp_path / "run")

    def refused(*args: str) -> str:
        res = CliRunner().invoke(cli, ["train", str(cfg), "--out", out, *args])
        assert res.exit_code != 0, res.output
        return res.output

    assert "add --executor local|slurm" in refused("--gpus", "2")
    assert "train the detector without it" in refused("--executor", "local", "--stage",
                                                      "detector")  # fmt: skip
    assert "cannot be split over 3 processes" in refused(*JOB[:2], "--tasks-per-node", "3")
    assert "leave --device out" in refused("--executor", "local", "--device", "cuda")
    assert "--nodes and --no-wait need --executor slurm" in refused(*JOB[:2], "--no-wait")
    if not torch.cuda.is_available():
        assert "needs 1 CUDA GPU(s) on this machine; found 0" in refused(*JOB[:2], "--gpus", "1")
    monkeypatch.setitem(sys.modules, "submitit", None)  # the cluster extra is not installed
    assert 'pip install "freipose[cluster]"' in refused("--executor", "slurm")
    assert not (tmp_path / "run").exists()
    monkeypatch.delitem(sys.modules, "submitit")
    plan = tmp_path / "poses" / ".jobs" / "plan.json"  # another command's job
    plan.parent.mkdir(parents=True)
    plan.write_text('{"command": "predict"}')
    res = CliRunner().invoke(cli, ["train", str(cfg), "--out", str(plan.parents[1]), *JOB])
    assert res.exit_code != 0 and "holds the job of `freipose predict`" in res.output


@pytest.mark.gpu
def test_local_job_on_this_machines_gpus(tmp_path):
    """One process per GPU (at most 2; NCCL with 2), each on its own device."""
    gpus = min(torch.cuda.device_count(), 2)
    cfg = train_config(tmp_path, steps=4, checkpoint_every=2)
    out = tmp_path / "run"
    args = ["-q", "train", str(cfg), "--out", str(out), "--executor", "local", "--gpus", str(gpus)]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 0, res.output
    assert f"1 node(s) x {gpus} process(es) on GPUs" in res.output
    assert read_checkpoint(out / "model.pt")["step"] == 4 and logged_steps(out) == [1, 2, 3, 4]


def test_a_job_that_ended_unwatched_is_journaled_done(tmp_path):
    """A job that wrote model.pt while no command watched it ends in the journal as done."""
    from freipose.cluster.config import ClusterConfig
    from freipose.cluster.driver import journal
    from freipose.cluster.train import TrainTask, run_train

    out = tmp_path / "run"
    task = TrainTask(config=tmp_path / "train.toml", out=out, kind=None, init=None,
                     device="cpu", nodes=1, tasks_per_node=1, threads=1, steps=2,
                     executor="slurm")  # fmt: skip
    journal(out, "submitted", unit="train", job_id="41", attempt=1, executor="slurm")
    (out / "model.pt").write_bytes(b"written by the job")
    said: list[str] = []
    res = run_train(task, ClusterConfig(executor="slurm"), say=said.append)
    assert res.model == out / "model.pt" and res.submitted == 0
    assert "the run is complete" in said[0]
    assert [(e["event"], e.get("job_id")) for e in read_journal(out)] == [
        ("submitted", "41"), ("done", "41")]  # fmt: skip
    run_train(task, ClusterConfig(executor="slurm"), say=said.append)
    assert len(read_journal(out)) == 2  # journaled once
