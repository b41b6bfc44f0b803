"""The engines that run units: worker processes here, or SLURM through submitit.

Both take a picklable function and one argument per unit, and answer, when asked, whether
each unit's job is queued, running or has ended (and why it ended, where the scheduler
says). Whether a unit *succeeded* is never taken from the engine: the driver looks at the
unit's output on disk (see :mod:`freipose.cluster.driver`), so a job that the scheduler
reports as failed after it wrote its part counts as done, and one that reports success
without its part counts as failed.

SLURM jobs are submitted with `submitit <https://github.com/facebookincubator/submitit>`_
(``pip install "freipose[cluster]"``): it writes the batch script, pickles the function and
its argument, keeps one log per task and reruns a requeued task. Their state is read with
``squeue`` (a task that is no longer listed has ended) and, for the reason of the end,
with ``sacct`` where the cluster keeps accounting, else ``scontrol``.
"""

from __future__ import annotations

import concurrent.futures
import logging
import shutil
import subprocess
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from freipose.cluster.config import ClusterConfig
from freipose.errors import FreiPoseError

log = logging.getLogger(__name__)

QUEUED, RUNNING, ENDED = "queued", "running", "ended"
Fn = Callable[[Any], Any]


class ExecutorError(FreiPoseError):
    """The engine cannot be used: not installed, no scheduler, or a submission failed."""


@dataclass(frozen=True)
class Ticket:
    """One submitted unit.

    Attributes:
        unit: the unit's name.
        job_id: the engine's id of its job (SLURM: ``"<array id>_<task>"``).
        log: the job's log file (SLURM: its stderr; None for worker processes).
    """

    unit: str
    job_id: str
    log: Path | None = None


@dataclass(frozen=True)
class JobState:
    """What the engine says of a job.

    Attributes:
        state: ``"queued"``, ``"running"`` or ``"ended"``.
        reason: the scheduler's state or reason (``PENDING (Resources)``, ``CANCELLED``,
            ``TIMEOUT``) or the error the unit raised; empty where none is known.
    """

    state: str
    reason: str = ""


class Executor(Protocol):
    """An engine that runs ``fn(arg)`` for each unit."""

    name: str

    def submit(self, fn: Fn, args: Sequence[Any], units: Sequence[str]) -> list[Ticket]:
        """Start one job per unit; returns their tickets in order."""

    def states(self, tickets: Sequence[Ticket]) -> dict[str, JobState]:
        """Job id -> its state, for every ticket."""

    def wait(self, tickets: Sequence[Ticket], timeout: float) -> None:
        """Return when a job may have ended, at the latest after ``timeout`` seconds."""

    def close(self) -> None:
        """Release the engine's resources (worker processes); jobs on a cluster go on."""


class LocalExecutor:
    """Units in worker processes on this machine, ``config.array_parallelism`` at a time."""

    name = "local"

    def __init__(self, config: ClusterConfig):
        from freipose.workers import process_pool

        self._pool: ProcessPoolExecutor = process_pool(
            config.array_parallelism, preload=("freipose.cluster.predict",)
        )
        self._futures: dict[str, Future] = {}
        self._count = 0

    def submit(self, fn: Fn, args: Sequence[Any], units: Sequence[str]) -> list[Ticket]:
        """Queue ``fn(arg)`` for each unit in the pool."""
        tickets = []
        for arg, unit in zip(args, units, strict=True):
            self._count += 1
            job_id = f"local-{self._count}"
            self._futures[job_id] = self._pool.submit(fn, arg)
            tickets.append(Ticket(unit, job_id))
        return tickets

    def states(self, tickets: Sequence[Ticket]) -> dict[str, JobState]:
        """Queued or running while the future is, else ended with the error it raised."""
        out = {}
        for t in tickets:
            fut = self._futures[t.job_id]
            if not fut.done():
                out[t.job_id] = JobState(RUNNING if fut.running() else QUEUED)
                continue
            exc = fut.exception()
            out[t.job_id] = JobState(ENDED, "" if exc is None else f"{type(exc).__name__}: {exc}")
        return out

    def wait(self, tickets: Sequence[Ticket], timeout: float) -> None:
        """Return as soon as one of the jobs ends, at the latest after ``timeout`` seconds."""
        futures = [self._futures[t.job_id] for t in tickets]
        concurrent.futures.wait(futures, timeout, return_when=concurrent.futures.FIRST_COMPLETED)

    def close(self) -> None:
        """Stop the worker processes (after the queued units)."""
        self._pool.shutdown(wait=True, cancel_futures=True)


def _run(cmd: list[str]) -> str | None:
    """The standard output of ``cmd``, or None where it fails or is not installed."""
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return res.stdout if res.returncode == 0 else None


def squeue_states(job_ids: Sequence[str]) -> dict[str, JobState] | None:
    """The jobs among ``job_ids`` that SLURM still lists (queued, running, requeued).

    Array tasks are listed one per line (``squeue -r``). None when ``squeue`` fails.
    """
    if not job_ids:
        return {}
    arrays = sorted({j.split("_")[0] for j in job_ids})
    out = _run(["squeue", "-h", "-r", "-j", ",".join(arrays), "-o", "%i|%T|%r"])
    if out is None:
        return None
    listed = {}
    for line in out.splitlines():
        parts = line.strip().split("|")
        if len(parts) != 3:
            continue
        job, state, reason = parts
        kind = RUNNING if state in ("RUNNING", "COMPLETING", "CONFIGURING") else QUEUED
        listed[job] = JobState(kind, state if reason in ("None", "") else f"{state} ({reason})")
    return {j: listed[j] for j in job_ids if j in listed}


def ended_reason(job_id: str) -> str:
    """Why a SLURM job ended: ``sacct``'s state where accounting is kept, else ``scontrol``'s."""
    out = _run(["sacct", "-n", "-X", "-P", "-j", job_id, "-o", "State,ExitCode"])
    if out and out.strip():
        state, _, code = out.strip().splitlines()[-1].partition("|")
        return f"{state} (exit code {code})"
    out = _run(["scontrol", "-o", "show", "job", job_id])
    if out:
        fields = dict(w.split("=", 1) for w in out.split() if "=" in w)
        state = fields.get("JobState", "")
        reason = fields.get("Reason", "None")
        return state if reason == "None" else f"{state} ({reason})"
    return ""


class SlurmExecutor:
    """Units as a SLURM job array submitted with submitit."""

    name = "slurm"

    def __init__(self, config: ClusterConfig, folder: Path, **parameters: Any):
        """Jobs with ``config``'s settings, their logs under ``folder``.

        Args:
            config: the cluster settings.
            folder: where submitit keeps the jobs' scripts, pickles and logs.
            parameters: further submitit parameters, over ``config``'s (``nodes``,
                ``ntasks_per_node``, ``srun_args``, ``job_name``).
        """
        try:
            import submitit
        except ImportError:
            raise ExecutorError(
                'the slurm executor needs submitit: pip install "freipose[cluster]" (or use '
                "--executor local)"
            ) from None
        if shutil.which("sbatch") is None or shutil.which("squeue") is None:
            raise ExecutorError(
                "the slurm executor needs SLURM's sbatch and squeue on this machine's PATH; run "
                "the command on the cluster's login node, or use --executor local"
            )
        self._submitit = submitit
        self._ex = submitit.SlurmExecutor(folder=str(folder / "%j"), max_num_timeout=3)
        params: dict[str, Any] = {
            "cpus_per_task": config.cpus,
            "mem": f"{int(config.mem_gb * 1024)}M",
            "time": config.time_min,
            "array_parallelism": config.array_parallelism,
            "job_name": "freipose",
            "additional_parameters": dict(config.sbatch),
        }
        if config.gpus:
            params["gpus_per_node"] = config.gpus
        for key in ("partition", "account", "qos"):
            if getattr(config, key):
                params[key] = getattr(config, key)
        self._ex.update_parameters(**{**params, **parameters})
        self._jobs: dict[str, Any] = {}

    def submit(self, fn: Fn, args: Sequence[Any], units: Sequence[str]) -> list[Ticket]:
        """Submit one job array with a task per unit.

        Raises:
            ExecutorError: ``sbatch`` refused it (the message is SLURM's).
        """
        try:
            jobs = self._ex.map_array(fn, list(args))
        except Exception as exc:  # sbatch refused: a bad partition, account, limit...
            raise ExecutorError(f"SLURM refused the submission: {exc}") from exc
        tickets = []
        for job, unit in zip(jobs, units, strict=True):
            self._jobs[job.job_id] = job
            tickets.append(Ticket(unit, job.job_id, Path(job.paths.stderr)))
        return tickets

    def states(self, tickets: Sequence[Ticket]) -> dict[str, JobState]:
        """Listed by ``squeue``: queued or running; not listed: ended, with the reason."""
        ids = [t.job_id for t in tickets]
        listed = squeue_states(ids)
        if listed is None:  # squeue failed (controller busy): assume nothing ended
            return {j: JobState(QUEUED, "squeue did not answer") for j in ids}
        out = {}
        for j in ids:
            out[j] = listed[j] if j in listed else JobState(ENDED, self._why(j))
        return out

    def _why(self, job_id: str) -> str:
        """The scheduler's state and reason, and the error the unit raised where it did."""
        scheduler = ended_reason(job_id)
        job = self._jobs.get(job_id)
        error = ""
        if job is not None and Path(job.paths.result_pickle).exists():
            try:
                outcome, value = self._submitit.core.utils.pickle_load(job.paths.result_pickle)
            except Exception:  # a half-written result: the scheduler knows more
                outcome, value = "", None
            if outcome == "error":
                error = str(value).strip().splitlines()[-1] if str(value).strip() else "error"
        return "; ".join(r for r in (scheduler, error) if r)

    def wait(self, tickets: Sequence[Ticket], timeout: float) -> None:
        """Sleep ``timeout`` seconds (the scheduler is asked again after it)."""
        time.sleep(timeout)

    def close(self) -> None:
        """Nothing to release: the jobs run on in the cluster."""
