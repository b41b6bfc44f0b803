"""Units on a real SLURM scheduler (the single-node SLURM that ``.ci/run`` starts).

Two toy sessions of 5 units each are predicted through ``--executor slurm`` while the
test cancels one running unit (``scancel``) and requeues another (``scontrol requeue``);
the joined files must equal a direct run's bit for bit, with the cancelled unit run again
and the requeued one rerun by SLURM itself. SLURM holds a requeued job back for the
credential lifetime and its next backfill pass; the test releases it at once with
``scontrol update starttime=now``, as an administrator may.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import SESSIONS, cluster_file, predict_args, slurm_reason, squeue_state
from predict_helpers import h5_equal

from freipose.cluster.driver import read_journal

pytestmark = pytest.mark.slurm

STUDY = SESSIONS[:2]


@pytest.fixture(scope="module")
def slurm() -> None:
    reason = slurm_reason()
    if reason is not None:
        pytest.skip(reason)


def _running_units(out: Path) -> list[tuple[str, str]]:
    """(unit, job id) of the units whose job has started predicting, per their records."""
    found = []
    for f in sorted((out / ".jobs" / "units").glob("*.json")):
        try:
            doc = json.loads(f.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        if doc.get("state") == "running" and doc.get("job_id"):
            found.append((doc["unit"], doc["job_id"]))
    return found


def _listed(job_id: str) -> bool:
    out = subprocess.run(["squeue", "-h", "-r", "-j", job_id.split("_")[0], "-o", "%i"],
                         capture_output=True, text=True, check=False).stdout.split()  # fmt: skip
    return job_id in out


def _release_when_pending(job_id: str, wait_s: float = 30.0) -> None:
    """Once the requeued ``job_id`` is pending again, let it start now."""
    t_end = time.monotonic() + wait_s
    while time.monotonic() < t_end:
        if squeue_state(job_id) == "PENDING":
            subprocess.run(["scontrol", "update", f"jobid={job_id}", "starttime=now"],
                           check=False, capture_output=True)  # fmt: skip
            return
        time.sleep(0.1)


def _outcome(out: Path, job: str, wait_s: float = 10.0) -> str:
    """The driver's journal event (``failed`` or ``done``) for ``job``, once it has one."""
    t_end = time.monotonic() + wait_s
    while time.monotonic() < t_end:
        for e in read_journal(out):
            if e.get("job_id") == job and e["event"] in ("failed", "done"):
                return e["event"]
        time.sleep(0.2)
    return ""


def _interfere(proc: subprocess.Popen, out: Path, deadline: float) -> dict[str, tuple[str, str]]:
    """Cancel running units until one is stopped midway, then requeue a running one.

    A unit can finish between the test seeing it run and the scheduler stopping it; such a
    try is not counted. Returns action -> (unit, job id).
    """
    actions: dict[str, tuple[str, str]] = {}
    tried: set[str] = set()
    while proc.poll() is None and time.monotonic() < deadline and len(actions) < 2:
        for unit, job in _running_units(out):
            if job in tried or not _listed(job):
                continue
            tried.add(job)
            if "cancelled" not in actions:
                subprocess.run(["scancel", job], check=True)
                if _outcome(out, job) == "failed":
                    actions["cancelled"] = (unit, job)
            else:
                subprocess.run(["scontrol", "requeue", job], check=True)
                _release_when_pending(job)
                actions["requeued"] = (unit, job)
            break
        time.sleep(0.1)
    return actions


@pytest.mark.slow
def test_slurm_units_survive_cancel_and_requeue(slurm, toy_study, tmp_path):
    out = tmp_path / "poses"
    cfg = cluster_file(tmp_path, executor="slurm", chunk_frames=8, array_parallelism=2,
                       poll_s=0.5, max_retries=2, cpus=1, mem_gb=1, time_min=10)  # fmt: skip
    study = {**toy_study, "sessions": toy_study["sessions"][: len(STUDY)]}
    cmd = [sys.executable, "-m", "freipose.cli.main",
           *predict_args(study, out, "--cluster", str(cfg))]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        done = _interfere(proc, out, time.monotonic() + 300)
        output, _ = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, output
    assert set(done) >= {"cancelled", "requeued"}, (done, output)
    for s in STUDY:  # 2 sessions x 5 units, joined: equal to the direct run
        assert h5_equal(toy_study["direct"] / f"{s}.poses.h5", out / f"{s}.poses.h5") == []
    assert not list(out.glob("*.shard-*"))
    events = read_journal(out)
    unit, job = done["cancelled"]  # failed, submitted again, done
    cancelled = [e for e in events if e.get("unit") == unit]
    assert [e["event"] for e in cancelled][-2:] == ["submitted", "done"]
    failure = next(e for e in cancelled if e["event"] == "failed" and e["job_id"] == job)
    assert "CANCELLED" in failure["reason"], failure
    unit, job = done["requeued"]  # SLURM ran the same job again: no failure, no new job
    requeued = [e for e in events if e.get("unit") == unit]
    assert [e["event"] for e in requeued] == ["submitted", "done"], requeued
    log = Path(requeued[0]["log"]).read_text()
    assert "DUE TO JOB REQUEUE" in log, log
    joined = [e["session"] for e in events if e["event"] == "joined"]
    assert sorted(joined) == list(STUDY)
    status = subprocess.run([sys.executable, "-m", "freipose.cli.main", "jobs", str(out)],
                            capture_output=True, text=True, check=True).stdout  # fmt: skip
    assert all(f"{s}: 5 done" in status for s in STUDY), status
