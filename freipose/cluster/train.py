"""``freipose train --executor ...``: the DDP training as one job of several processes.

The job runs ``nodes x tasks_per_node`` processes, one per GPU (or CPU processes that
average their gradients with gloo when no GPU is asked for); they form the process group
of :mod:`freipose.nn.train`, which splits the global batch over them and averages the
gradients with DistributedDataParallel. On SLURM, submitit starts the processes
(``srun``, one task per process) and ``submitit.helpers.TorchDistributedEnvironment``
gives each its rank, the world size and the first node's address; on the local executor
the job starts its processes on this machine.

The job is resumable: its processes train on from ``RUN/checkpoint.pt`` where it exists
(written atomically every ``schedule.checkpoint_every`` steps), and a resumed run equals
the uninterrupted run bit for bit (same processes, same threads). A job that SLURM
requeues (``scontrol requeue``, preemption) starts again and continues from there; near
its time limit submitit signals it, calls :meth:`TrainJob.checkpoint` and requeues it. A
job that ends without ``model.pt`` in any other way (cancelled, failed, node lost) is
submitted again, at most ``max_retries`` times, and running the same command again
continues the run or reports it complete.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import signal
import socket
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from freipose.cluster.config import ClusterConfig
from freipose.cluster.driver import JOBS_DIR, Unit, journal, now_iso, read_journal, run_units
from freipose.cluster.executors import (
    Executor,
    LocalExecutor,
    SlurmExecutor,
    Ticket,
    squeue_states,
)
from freipose.errors import FreiPoseError
from freipose.io.atomic import atomic_write_text
from freipose.io.lock import output_lock

PLAN_FILE = "plan.json"
UNIT = "train"


class TrainJobError(FreiPoseError):
    """The training job cannot be submitted, or ended without its model after its retries."""


class TrainStopped(Exception):
    """SLURM ended the job (cancelled, requeued, preempted): ``checkpoint.pt`` is kept."""


@dataclass(frozen=True)
class TrainTask:
    """What every process of the training job needs.

    Attributes:
        config: the training config (absolute path).
        out: the run folder (absolute path).
        kind: ``"baseline"`` to train the baseline network, None for the config's kind.
        init: the starting weights instead of the config's ``model.init`` (None: its own).
        device: ``"cuda"`` (one GPU per process) or ``"cpu"``.
        nodes: machines of the job.
        tasks_per_node: processes per machine.
        threads: PyTorch and OpenCV threads of each process.
        steps: the schedule's steps (to show the progress).
        executor: ``"local"`` or ``"slurm"``.
    """

    config: Path
    out: Path
    kind: str | None
    init: str | None
    device: str
    nodes: int
    tasks_per_node: int
    threads: int
    steps: int
    executor: str

    @property
    def world(self) -> int:
        """The number of processes."""
        return self.nodes * self.tasks_per_node

    def model(self) -> Path:
        """The final checkpoint, written once the run is complete."""
        return self.out / "model.pt"


def _stop_on_sigterm() -> None:
    """Stop at once on SLURM's SIGTERM (cancel, requeue, preemption) instead of at SIGKILL.

    The exception unwinds the run folder's lock, so the next job (on any node) can take it;
    the steps since the last ``checkpoint.pt`` are done again.
    """

    def stop(signum: int, frame: Any) -> None:
        raise TrainStopped(f"stopped by SLURM (signal {signum}); checkpoint.pt is kept")

    signal.signal(signal.SIGTERM, stop)


def _train_process(task: TrainTask) -> str:
    """Train as one process of the job (its rank is in the environment); returns the output."""
    import cv2
    import torch
    import torch.distributed as dist

    from freipose.nn.train import train_from_config

    torch.set_num_threads(task.threads)
    cv2.setNumThreads(task.threads)
    resume = (task.out / "checkpoint.pt").exists()
    try:
        path = train_from_config(task.config, task.out, resume=resume, device=task.device,
                                 kind=task.kind, progress=False, init=task.init)  # fmt: skip
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()
    return str(path)


def _spawned_process(rank: int, task: TrainTask, port: int, parent: int) -> None:
    """Process ``rank`` of a job on this machine (started by ``torch.multiprocessing``)."""
    from freipose.workers import die_with

    die_with(parent)
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank),
                      WORLD_SIZE=str(task.world), LOCAL_RANK=str(rank),
                      LOCAL_WORLD_SIZE=str(task.world))  # fmt: skip
    _train_process(task)


def _free_port() -> int:
    """A TCP port of this machine that nothing listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class TrainJob:
    """The job's callable: ``TrainJob()(task)`` trains ``task`` as the job's processes.

    On SLURM every task of the job calls it; on the local executor it starts the processes
    itself. Its :meth:`checkpoint` makes it what submitit calls checkpointable (the method
    of ``submitit.helpers.Checkpointable``): before the time limit submitit requeues it
    with the same task, and the processes continue from ``checkpoint.pt``.
    """

    def __call__(self, task: TrainTask) -> str:
        """Train; returns the path of the checkpoint written last (``model.pt`` when done)."""
        if task.executor == "slurm":
            from submitit.helpers import TorchDistributedEnvironment

            # the job's log says what it does ("resuming RUN at step S of N")
            logging.basicConfig(level=logging.INFO, format="%(levelname)s: %(message)s")
            _stop_on_sigterm()
            TorchDistributedEnvironment().export(set_cuda_visible_devices=False, overwrite=True)
            return _train_process(task)
        if task.world == 1:
            return _train_process(task)
        import torch.multiprocessing as mp

        try:
            mp.spawn(_spawned_process, args=(task, _free_port(), os.getpid()), nprocs=task.world)
        except mp.ProcessRaisedException as exc:  # the rank's error, without the traceback
            raise TrainJobError(str(exc).strip().splitlines()[-1]) from None
        return str(task.model())

    def checkpoint(self, task: TrainTask) -> Any:
        """The same job again (submitit requeues it; it resumes from ``checkpoint.pt``)."""
        from submitit.helpers import DelayedSubmission

        return DelayedSubmission(self, task)


def _plan_path(out: Path) -> Path:
    return out / JOBS_DIR / PLAN_FILE


def _save_plan(task: TrainTask, config: ClusterConfig) -> None:
    """``RUN/.jobs/plan.json``: the task and the settings, for ``freipose jobs``."""
    doc = {"command": "train", "created": now_iso(), "cluster": dataclasses.asdict(config),
           "task": dataclasses.asdict(task)}  # fmt: skip
    path = _plan_path(task.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(doc, indent=1, default=str))


def _refuse_other_job(out: Path) -> None:
    """Refuse a run folder that holds another command's job (one job per folder).

    Raises:
        TrainJobError: ``RUN/.jobs`` holds the job of another command.
    """
    try:
        other = json.loads(_plan_path(out).read_text(encoding="utf-8")).get("command", "train")
    except (OSError, ValueError):
        return
    if other != "train":
        raise TrainJobError(
            f"{out} holds the job of `freipose {other}` ({_plan_path(out)}); train into "
            "another folder (--out)"
        )


def is_train_job(out: Path) -> bool:
    """Whether ``out`` holds a training job of ``freipose train --executor``."""
    try:
        doc = json.loads(_plan_path(Path(out)).read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return False
    return doc.get("command") == "train"


def load_train_task(out: Path) -> tuple[TrainTask, ClusterConfig]:
    """The task and the cluster settings of the training job in ``out``.

    Raises:
        TrainJobError: ``out`` holds no training job.
    """
    if not is_train_job(out):
        raise TrainJobError(
            f"{out}: no training job found (no {JOBS_DIR}/{PLAN_FILE}); it is written by "
            "`freipose train CONFIG --out RUN --executor local|slurm`"
        )
    doc = json.loads(_plan_path(Path(out)).read_text(encoding="utf-8"))
    t = doc["task"]
    task = TrainTask(**{**t, "config": Path(t["config"]), "out": Path(t["out"])})
    return task, ClusterConfig(**doc["cluster"])


def last_step(task: TrainTask) -> int:
    """The last step written to ``RUN/log.csv`` (0 before any)."""
    from freipose.nn.train_log import read_log

    try:
        rows = read_log(task.out / "log.csv", task.steps)
    except (OSError, ValueError):  # a row being written
        return 0
    return int(rows[-1]["step"]) if rows else 0


def _last_job(task: TrainTask) -> dict[str, Any] | None:
    """The journal's last submission, with ``attempts``, ``ended`` and the ``reason``."""
    from freipose.cluster.status import _last_jobs

    return _last_jobs(read_journal(task.out)).get(UNIT)


@dataclass(frozen=True)
class TrainJobStatus:
    """The state of a training job.

    Attributes:
        task: the job's task.
        executor: ``"local"`` or ``"slurm"``.
        state: ``done``, ``running``, ``queued``, ``failed`` or ``waiting`` (never submitted).
        step: the last step in the run's log.
        job_id: its last job ('' before any).
        attempts: jobs it was given.
        reason: the scheduler's state or reason, or the job's error.
        log: the last job's log file.
    """

    task: TrainTask
    executor: str
    state: str
    step: int
    job_id: str = ""
    attempts: int = 0
    reason: str = ""
    log: str = ""


def train_job_status(out: Path) -> TrainJobStatus:
    """The state of the training job in ``out``, from its files, journal and scheduler.

    Raises:
        TrainJobError: ``out`` holds no training job.
    """
    task, config = load_train_task(Path(out))
    job = _last_job(task)
    step = last_step(task)
    if task.model().is_file():
        state, reason = "done", ""
    elif job is None:
        state, reason = "waiting", ""
    else:
        listed = squeue_states([job["job_id"]]) if config.executor == "slurm" else None
        if listed is not None and job["job_id"] in listed:
            js = listed[job["job_id"]]
            state, reason = ("running" if js.state == "running" else "queued"), js.reason
        elif job["ended"] or listed is not None:
            state, reason = "failed", job.get("reason") or "ended without model.pt"
        else:  # a local job runs while the command that started it runs
            state, reason = "running", "while its command runs"
    common = {"job_id": job["job_id"], "attempts": job["attempts"],
              "log": str(job.get("log") or "")} if job else {}  # fmt: skip
    return TrainJobStatus(task, config.executor, state, step, reason=reason, **common)


@dataclass(frozen=True)
class ClusterTrainResult:
    """What ``train`` through an executor did.

    Attributes:
        model: the final checkpoint (None: the job was submitted without waiting for it).
        job_id: the last job's id ('' when the run was complete before).
        submitted: jobs submitted by this command.
    """

    model: Path | None
    job_id: str
    submitted: int


class _Watched:
    """An executor that shows the run's step while it waits and says what it submits."""

    def __init__(self, inner: Executor, show: Callable[[], None], say: Callable[[str], None]):
        self._inner, self._show, self._say = inner, show, say
        self.name = inner.name
        self.job_id = ""

    def submit(self, fn: Any, args: Sequence[Any], units: Sequence[str]) -> list[Ticket]:
        tickets = self._inner.submit(fn, args, units)
        for t in tickets:
            self.job_id = t.job_id
            self._say(f"job {t.job_id} submitted" + (f"; log {t.log}" if t.log else ""))
        return tickets

    def states(self, tickets: Sequence[Ticket]) -> dict[str, Any]:
        return self._inner.states(tickets)

    def wait(self, tickets: Sequence[Ticket], timeout: float) -> None:
        self._inner.wait(tickets, timeout)
        self._show()

    def close(self) -> None:
        self._inner.close()


def make_train_executor(task: TrainTask, config: ClusterConfig) -> Executor:
    """The engine of the job: a worker process here, or SLURM with nodes and tasks.

    Raises:
        ExecutorError: submitit or SLURM is not there.
    """
    if config.executor == "slurm":
        return SlurmExecutor(
            config, task.out / JOBS_DIR / "slurm", nodes=task.nodes, job_name="freipose-train",
            ntasks_per_node=task.tasks_per_node, array_parallelism=1,
            srun_args=["--kill-on-bad-exit=1"],  # a process that fails ends the others
        )  # fmt: skip
    return LocalExecutor(config.replace(array_parallelism=1))


def _wait_for_listed(task: TrainTask, job: dict[str, Any], config: ClusterConfig,
                     show: Callable[[], None]) -> None:  # fmt: skip
    """Wait while SLURM lists ``job`` (an earlier command's), then journal how it ended."""
    import time

    from freipose.cluster.executors import ended_reason

    while (squeue_states([job["job_id"]]) or {}).get(job["job_id"]) is not None:
        show()
        time.sleep(config.poll_s)
    if task.model().is_file():
        journal(task.out, "done", unit=UNIT, job_id=job["job_id"])
    else:
        reason = ended_reason(job["job_id"]) or "ended without model.pt"
        journal(task.out, "failed", unit=UNIT, job_id=job["job_id"], reason=reason,
                log=job.get("log"))  # fmt: skip


def _journal_unwatched_end(task: TrainTask) -> None:
    """Journal ``done`` for a job that wrote the model while no command watched it."""
    job = _last_job(task)
    if job is not None and not job["ended"] and task.model().is_file():
        journal(task.out, "done", unit=UNIT, job_id=job["job_id"])


def _running_job(task: TrainTask, config: ClusterConfig) -> tuple[dict[str, Any], str] | None:
    """The job of an earlier command that SLURM still lists, with its state; else None."""
    job = _last_job(task)
    if job is None or config.executor != "slurm":
        return None
    listed = squeue_states([job["job_id"]]) or {}
    return (job, listed[job["job_id"]].reason) if job["job_id"] in listed else None


def run_train(
    task: TrainTask,
    config: ClusterConfig,
    wait: bool = True,
    progress: bool = True,
    say: Callable[[str], None] = print,
) -> ClusterTrainResult:
    """Train ``task`` as a job on the executor ``config`` names.

    A run whose ``model.pt`` exists is reported and not submitted; a job of an earlier
    command that SLURM still lists is waited for (or reported, without ``wait``) instead of
    submitting a second one.

    Args:
        task: the training and its processes.
        config: the executor and its settings.
        wait: wait for the job (showing its step), resubmitting it when it ends without
            its model; False: submit and return (SLURM only).
        progress: show the steps.
        say: where the messages go.

    Raises:
        TrainJobError: the job ended without its model after its retries, or the run
            folder holds another command's job.
        ExecutorError: the engine cannot be used.
        OutputLockedError: another command drives a job in the same run folder.
    """
    from freipose.progress import progress_bar

    _refuse_other_job(task.out)
    if task.model().is_file():
        _journal_unwatched_end(task)
        say(f"{task.out}: the run is complete ({task.model()}); nothing to submit")
        return ClusterTrainResult(task.model(), "", 0)
    inner = make_train_executor(task, config)  # before anything is written
    bar = progress_bar(total=task.steps, initial=last_step(task), unit="step",
                       desc=f"train ({config.executor})",
                       disable=not (progress and wait) or None)  # fmt: skip

    def show() -> None:
        bar.update(max(0, last_step(task) - bar.n))

    executor = _Watched(inner, show, say)
    try:
        with output_lock(task.out / JOBS_DIR / "driver", "job driver", option="--out"), bar:
            _save_plan(task, config)
            running = _running_job(task, config)
            if running is not None:
                say(f"job {running[0]['job_id']} of this run is {running[1]}")
                if not wait:
                    return ClusterTrainResult(None, running[0]["job_id"], 0)
                _wait_for_listed(task, running[0], config, show)
                if task.model().is_file():
                    return ClusterTrainResult(task.model(), running[0]["job_id"], 0)
            if not wait:
                (ticket,) = executor.submit(TrainJob(), [task], [UNIT])
                journal(task.out, "submitted", unit=UNIT, job_id=ticket.job_id,
                        log=ticket.log, attempt=1, executor=executor.name)  # fmt: skip
                return ClusterTrainResult(None, ticket.job_id, 1)
            report = run_units(
                [Unit(UNIT, UNIT, 0, 1, task.steps)], TrainJob(), lambda u: task,
                lambda u: task.model().is_file(), executor, task.out,
                max_retries=config.max_retries, poll_s=config.poll_s, progress=False,
            )  # fmt: skip
            show()
            _journal_unwatched_end(task)
    finally:
        executor.close()
    if report.failed:
        f = report.failed[0]
        kept = "checkpoint.pt is kept: " if (task.out / "checkpoint.pt").exists() else ""
        raise TrainJobError(
            f"the training job ended without {task.model().name} after {f.attempts} jobs: "
            f"{f.reason} (log: {f.log or '-'}); {kept}fix the cause and run the command "
            f"again, or `freipose jobs {task.out} --resume`"
        )
    return ClusterTrainResult(task.model(), executor.job_id, report.submitted)
