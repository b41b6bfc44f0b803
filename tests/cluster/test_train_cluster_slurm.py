"""A training job of 2 gloo processes on a real SLURM (the single-node SLURM of ``.ci/run``).

A run is submitted with ``--no-wait``, waited for by the same command (which must not
submit it twice), requeued midway (``scontrol requeue``: SIGTERM, then the same job again)
and later signalled as at its time limit; it must continue from its checkpoints to the
weights of the same training run uninterrupted as a local job of 2 processes (``gloo_run``
in ``conftest.py``), bit for bit. SLURM holds a requeued job back for the credential
lifetime (its BeginTime; two minutes by default, 15 s on the SLURM of ``.ci/start-slurm``);
the test releases it at once with ``scontrol update starttime=now``, as an administrator
may.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import (
    EVERY,
    STEPS,
    cluster_file,
    logged_steps,
    same_weights,
    slurm_reason,
    squeue_state,
    train_config,
)

from freipose.cluster.driver import read_journal

pytestmark = pytest.mark.slurm


@pytest.fixture(scope="module")
def slurm() -> None:
    reason = slurm_reason()
    if reason is not None:
        pytest.skip(reason)


def _cli(*args: object, timeout: float = 300) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "freipose.cli.main", "-q", *map(str, args)]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=False)


def _until(what: str, ok, deadline: float) -> None:  # noqa: ANN001 - a callable
    while not ok():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.1)


def _job_id(run: Path) -> str:
    found = [e["job_id"] for e in read_journal(run) if e["event"] == "submitted"]
    return found[-1] if found else ""


def _last_step(run: Path) -> int:
    try:
        steps = logged_steps(run)
    except (OSError, ValueError):
        return 0
    return steps[-1] if steps else 0


def _interrupted(
    cfg: Path, run: Path, job: list, interrupts: list[tuple[int, list[str]]]
) -> tuple[str, list[int]]:
    """Submit the training into ``run`` with ``--no-wait``, then wait for it with the same
    command, interrupting its job at each ``(step, command)`` of ``interrupts`` once the run
    has logged that step.

    Returns:
        The job's id and, per interrupt, the last step the run had logged once the job was
        stopped (the job runs on while the signal is on its way: it may checkpoint a step
        after the one read before the interrupt).
    """
    deadline = time.monotonic() + 300
    res = _cli("train", cfg, "--out", run, *job, "--no-wait")
    assert res.returncode == 0 and "follow it with: freipose jobs" in res.stdout, res
    job_id = _job_id(run)
    res = _cli("jobs", run)
    assert f"job {job_id} (attempt 1)" in res.stdout, res
    assert ": queued" in res.stdout or ": running" in res.stdout, res.stdout
    cmd = [sys.executable, "-m", "freipose.cli.main", "-q", "train", str(cfg), "--out",
           str(run), *map(str, job)]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    stopped = []
    try:
        for at, interrupt in interrupts:
            _until(f"the job's step {at}",
                   lambda at=at: _last_step(run) >= at or proc.poll() is not None,
                   deadline)  # fmt: skip
            step = _last_step(run)
            assert step < STEPS, f"the run ended (step {step}) before the test could interrupt it"
            subprocess.run([*interrupt, job_id], check=True)
            _until("the requeued job", lambda: squeue_state(job_id) == "PENDING", deadline)
            stopped.append(_last_step(run))  # no step is logged until it starts again
            subprocess.run(["scontrol", "update", f"jobid={job_id}", "starttime=now"],
                           check=True)  # fmt: skip
        output, _ = proc.communicate(timeout=max(deadline - time.monotonic(), 1))
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, output
    return job_id, stopped


@pytest.mark.slow
def test_slurm_training_requeued_midway_equals_an_uninterrupted_run(slurm, gloo_run, tmp_path):
    """A job requeued by SLURM, then signalled as at its time limit, resumes bit for bit.

    The run is submitted with ``--no-wait``, waited for by the same command (which must not
    submit it twice) and interrupted twice: ``scontrol requeue`` (SIGTERM, then SLURM starts
    the same job again) after step 6, and USR2 (submitit's signal before the time limit, on
    which it calls TrainJob.checkpoint and requeues the job; a job that is not
    checkpointable would end and be submitted again: 2 jobs) after step 18. Its weights
    equal those of the uninterrupted local job of ``gloo_run``: same processes, same
    threads. Three job starts of 2 processes on the node's 2 cores, mostly the 10-15 s
    from a job's start to its first step (Python, PyTorch, the process group).
    """
    cfg = train_config(tmp_path, steps=STEPS, checkpoint_every=EVERY)
    cl = cluster_file(tmp_path, poll_s=0.5, cpus=1, mem_gb=2, time_min=10)
    job = ["--executor", "slurm", "--cluster", cl, "--tasks-per-node", "2"]
    ref = gloo_run["run"]
    run = tmp_path / "run"
    interrupts = [(6, ["scontrol", "requeue"]), (18, ["scancel", "--signal=USR2"])]
    job_id, stopped = _interrupted(cfg, run, job, interrupts)
    assert same_weights(ref / "model.pt", run / "model.pt")
    assert logged_steps(run) == list(range(1, STEPS + 1))
    assert [e["event"] for e in read_journal(run)] == ["submitted", "done"]
    log = next((run / ".jobs" / "slurm").glob(f"{job_id}/*_0_log.err")).read_text()
    assert "DUE TO JOB REQUEUE" in log, log  # after USR2: requeued by submitit itself
    resumed = [int(s) for s in re.findall(rf"resuming \S+ at step (\d+) of {STEPS}", log)]
    assert len(resumed) == 2, log
    for at, (first, step) in zip(resumed, zip([6, 18], stopped, strict=True), strict=True):
        assert first - EVERY < at <= step and at % EVERY == 0, (resumed, stopped, log)
