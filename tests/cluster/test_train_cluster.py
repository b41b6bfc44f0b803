"""``freipose train --executor local``: two gloo processes as a job, resumed bit for bit.

The job's run equals two processes launched directly (the way ``torchrun`` does) that
were stopped after a checkpoint and continued by the job; a second run of the command
reports the run complete; ``freipose jobs RUN`` shows the job; bad requests are refused
before anything is submitted.
"""

from __future__ import annotations

import socket
import sys
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "nn"))

from nn_toydata import toy_samples, write_toy_labels  # noqa: E402

from freipose.cli.main import cli  # noqa: E402
from freipose.cluster.driver import read_journal  # noqa: E402
from freipose.nn.checkpoint import read_checkpoint  # noqa: E402

JOB = ["--executor", "local", "--tasks-per-node", "2", "--threads", "1"]


def train_config(folder: Path, steps: int, checkpoint_every: int) -> Path:
    """A tiny training config on 4 toy samples, global batch 4 (2 per process)."""
    write_toy_labels(folder / "data", toy_samples(4))
    path = folder / "cfg.toml"
    path.write_text(
        '[data]\nlabels = "data/labels.h5"\n'
        '[model]\npreset = "tiny"\ncube_size = 300.0\ninit = "scratch"\n'
        f"[schedule]\nsteps = {steps}\ncheckpoint_every = {checkpoint_every}\nbatch_size = 4\n"
        "[augment]\nenabled = false\n"
    )
    return path


def same_weights(a: Path, b: Path) -> bool:
    """Whether two checkpoints hold the same weights, bit for bit."""
    wa, wb = read_checkpoint(a)["model"], read_checkpoint(b)["model"]
    return wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)


def logged_steps(run: Path) -> list[int]:
    """The steps of the run's log.csv, in order."""
    return [int(r.split(",")[0]) for r in (run / "log.csv").read_text().split()[1:]]


def _direct_process(rank: int, port: int, config: str, out: str, stop_after: int) -> None:
    """Process ``rank`` of 2 launched as torchrun would, stopped after ``stop_after`` steps."""
    import os

    from freipose.io.labels import read_labels_h5
    from freipose.nn.config import load_config
    from freipose.nn.dataset import MultiViewDataset
    from freipose.nn.train import train_pose
    from freipose.skeleton import Skeleton

    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank),
                      WORLD_SIZE="2")  # fmt: skip
    torch.set_num_threads(1)
    labels_path = Path(config).parent / "data" / "labels.h5"
    labels = read_labels_h5(labels_path)
    source = MultiViewDataset(labels, root=labels_path.parent)
    try:
        train_pose(load_config(config), out, source, Skeleton("labels", labels.keypoints),
                   progress=False, stop_after=stop_after)  # fmt: skip
    finally:
        torch.distributed.destroy_process_group()


def test_local_job_of_two_gloo_processes_continues_a_run_bit_for_bit(tmp_path):
    cfg = train_config(tmp_path, steps=4, checkpoint_every=2)
    runner = CliRunner()
    whole, part = tmp_path / "whole", tmp_path / "part"
    res = runner.invoke(cli, ["-q", "train", str(cfg), "--out", str(whole), *JOB])
    assert res.exit_code == 0, res.output
    assert "1 node(s) x 2 process(es) on CPUs" in res.output
    assert logged_steps(whole) == [1, 2, 3, 4]
    # two processes launched directly stop after step 2; the job continues their run
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    torch.multiprocessing.spawn(_direct_process, args=(port, str(cfg), str(part), 2), nprocs=2)
    assert read_checkpoint(part / "checkpoint.pt")["step"] == 2
    res = runner.invoke(cli, ["-q", "train", str(cfg), "--out", str(part), *JOB])
    assert res.exit_code != 0 and "pass --resume" in res.output, res.output
    res = runner.invoke(cli, ["-q", "train", str(cfg), "--out", str(part), *JOB, "--resume"])
    assert res.exit_code == 0, res.output
    assert same_weights(whole / "model.pt", part / "model.pt")
    assert logged_steps(part) == [1, 2, 3, 4]
    # the same command again: complete, nothing submitted
    res = runner.invoke(cli, ["-q", "train", str(cfg), "--out", str(whole), *JOB])
    assert res.exit_code == 0 and "the run is complete" in res.output, res.output
    assert [e["event"] for e in read_journal(whole)] == ["submitted", "done"]
    res = runner.invoke(cli, ["jobs", str(whole)])
    assert res.exit_code == 0, res.output
    assert "2 process(es)): done, step 4 of 4, job local-1 (attempt 1)" in res.output


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
