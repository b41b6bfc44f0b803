"""``freipose predict --executor ...``: sessions split into frame chunks run as units.

Each session's frames are cut into units of ``chunk_frames`` frames (whole batches, counted
from the start of the run's frame range); a unit is the prediction's shard primitive
(``--shard I/N``), so it writes ``OUTDIR/<session>.shard-I-of-N.poses.h5`` under that file's
lock, resumes a part written before it was killed, and is complete when the file says so.
Its batches are the batches of a single run over the whole session, so, with the same
number of threads per process, the units' joined file equals a single run's output value
for value. When every unit of a session is complete the driver joins them into
``OUTDIR/<session>.poses.h5``, checks that every frame is there exactly once, and removes
the parts.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import pickle
import signal
import socket
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from freipose.cluster.config import ClusterConfig
from freipose.cluster.driver import JOBS_DIR, DriverReport, Unit, journal, now_iso, run_units
from freipose.cluster.executors import Executor, LocalExecutor, SlurmExecutor
from freipose.errors import FreiPoseError
from freipose.io.atomic import atomic_path, atomic_write_text
from freipose.io.lock import output_lock
from freipose.io.session import Session
from freipose.io.video import frame_range

log = logging.getLogger(__name__)

TASK_FILE = "task.pkl"
PLAN_FILE = "plan.json"


class UnitStopped(Exception):
    """SLURM ended the unit's job (cancelled, preempted, out of time): its part stays resumable."""


def _stop_on_sigterm() -> None:
    """In a SLURM job, stop the unit at once on SIGTERM instead of running on to SIGKILL.

    SLURM sends SIGTERM when a job is cancelled, requeued, preempted or out of time, and
    SIGKILL a little later; submitit lets SIGTERM pass. Stopping at once closes the part
    after its last whole chunk, so the next job continues from there.
    """

    def stop(signum: int, frame: Any) -> None:
        raise UnitStopped(f"stopped by SLURM (signal {signum}); the part is kept for the next job")

    if "SLURM_JOB_ID" in os.environ:
        signal.signal(signal.SIGTERM, stop)


class UnitsFailedError(FreiPoseError):
    """Some units failed after their retries; the message names them and how to finish."""


@dataclass(frozen=True)
class PredictTask:
    """Everything every unit of one prediction needs (pickled into each job).

    Attributes:
        sessions: the validated sessions.
        model: the pose checkpoint.
        spec: how to find the animal (a ``freipose.predict.network.DetectorSpec``).
        outdir: the output folder.
        frames: ``START:STOP`` of every session (None: all).
        batch_size: time steps per network call.
        device: ``cpu``, ``cuda``, ``cuda:N`` or ``auto``.
        refine: report P1 (True) or P0.
        overrides: inference settings instead of the checkpoint's (None: its own).
        chunk_frames: frames per unit.
        threads: PyTorch and OpenCV threads of each unit.
        skeleton: the keypoints the model must predict (None: any).
    """

    sessions: tuple[Session, ...]
    model: Path
    spec: Any
    outdir: Path
    frames: str | None
    batch_size: int
    device: str
    refine: bool
    overrides: Any
    chunk_frames: int
    threads: int
    skeleton: Any = None

    def session(self, name: str) -> Session:
        """The session called ``name``."""
        return next(s for s in self.sessions if s.name == name)


@dataclass(frozen=True)
class UnitArg:
    """One unit's argument: the task and which chunk of which session.

    Attributes:
        task: the prediction.
        unit: the unit.
    """

    task: PredictTask
    unit: Unit


def plan_units(task: PredictTask) -> list[Unit]:
    """The units of ``task``: every session cut into whole-batch chunks of its frames."""
    from freipose.predict.run import commit_rows

    rows = commit_rows(task.batch_size, task.chunk_frames)
    units = []
    for s in task.sessions:
        r = frame_range(task.frames, s.num_frames)
        n = max(1, math.ceil((r.stop - r.start) / rows))
        for i in range(n):
            a, b = r.start + i * rows, min(r.start + (i + 1) * rows, r.stop)
            units.append(Unit(f"{s.name}.{i}-of-{n}", s.name, i, n, b - a))
    return units


def unit_output(task: PredictTask, unit: Unit) -> Path:
    """The file unit ``unit`` writes."""
    from freipose.predict.run import output_path

    return output_path(task.outdir, unit.session, (unit.index, unit.count))


def session_output(task: PredictTask, session: str) -> Path:
    """The joined file of a session."""
    from freipose.predict.run import output_path

    return output_path(task.outdir, session)


def unit_is_done(task: PredictTask, unit: Unit) -> bool:
    """Whether the unit's part is complete (or its session's joined file already is)."""
    from freipose.predict.writer import is_complete

    joined = session_output(task, unit.session)
    return (joined.exists() and is_complete(joined)) or (
        unit_output(task, unit).exists() and is_complete(unit_output(task, unit))
    )


def _unit_record(task: PredictTask, unit: Unit, **fields: Any) -> None:
    """Write what a unit is doing to ``OUTDIR/.jobs/units/<unit>.json`` (for the status)."""
    path = task.outdir / JOBS_DIR / "units" / f"{unit.name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps({"unit": unit.name, **fields}, indent=1))


def predict_unit(arg: UnitArg) -> int:
    """Predict one unit (run in a worker process or a SLURM job); returns its frames."""
    import cv2
    import torch

    from freipose.predict.network import predict_sessions

    task, unit = arg.task, arg.unit
    _stop_on_sigterm()
    torch.set_num_threads(task.threads)
    cv2.setNumThreads(task.threads)
    job = os.environ.get("SLURM_ARRAY_JOB_ID", os.environ.get("SLURM_JOB_ID", ""))
    if job and "SLURM_ARRAY_TASK_ID" in os.environ:
        job = f"{job}_{os.environ['SLURM_ARRAY_TASK_ID']}"
    where: dict[str, Any] = {"host": socket.gethostname(), "pid": os.getpid(), "job_id": job}
    t0 = time.perf_counter()
    first: list[float] = []
    where["started_at"] = time.time()
    _unit_record(task, unit, state="running", started=now_iso(), **where)
    predict_sessions(
        [task.session(unit.session)], task.model, task.spec, task.outdir, frames=task.frames,
        batch_size=task.batch_size, device=task.device, refine=task.refine,
        overrides=task.overrides, shard=(unit.index, unit.count),
        chunk_frames=task.chunk_frames, expected_skeleton=task.skeleton, progress=False,
        on_batch=lambda n: first.append(time.time()) if not first else None,
    )  # fmt: skip
    seconds = time.perf_counter() - t0
    _unit_record(task, unit, state="done", finished=now_iso(), seconds=round(seconds, 3),
                 first_frame_at=first[0] if first else None, frames=unit.frames,
                 **where)  # fmt: skip
    return unit.frames


@dataclass(frozen=True)
class ClusterPredictResult:
    """What ``predict`` through an executor did.

    Attributes:
        report: the driver's report.
        joined: the sessions' joined poses files (complete ones, new or earlier).
        frames: frames of all units.
    """

    report: DriverReport
    joined: tuple[Path, ...]
    frames: int


def make_executor(config: ClusterConfig, outdir: Path) -> Executor:
    """The engine ``config.executor`` names (its SLURM logs go under ``OUTDIR/.jobs/slurm``)."""
    if config.executor == "slurm":
        return SlurmExecutor(config, outdir / JOBS_DIR / "slurm")
    return LocalExecutor(config)


def _save_plan(task: PredictTask, config: ClusterConfig, units: Sequence[Unit]) -> None:
    """``OUTDIR/.jobs/plan.json`` (read by ``freipose jobs``) and the task for ``--resume``."""
    folder = task.outdir / JOBS_DIR
    folder.mkdir(parents=True, exist_ok=True)
    doc = {
        "command": "predict",
        "created": now_iso(),
        "cluster": dataclasses.asdict(config),
        "sessions": [s.name for s in task.sessions],
        "units": [dataclasses.asdict(u) for u in units],
    }
    atomic_write_text(folder / PLAN_FILE, json.dumps(doc, indent=1, default=str))
    with atomic_path(folder / TASK_FILE) as tmp:
        tmp.write_bytes(pickle.dumps(task))


def load_task(outdir: Path) -> tuple[PredictTask, ClusterConfig]:
    """The task and cluster settings saved by an earlier run into ``OUTDIR``.

    Raises:
        FreiPoseError: ``OUTDIR`` holds no job of ``freipose predict --executor``.
    """
    folder = Path(outdir) / JOBS_DIR
    if not (folder / TASK_FILE).is_file() or not (folder / PLAN_FILE).is_file():
        raise FreiPoseError(
            f"{outdir}: no job found (no {JOBS_DIR}/{PLAN_FILE}); it is written by "
            "`freipose predict ... --executor local|slurm -o OUTDIR`"
        )
    task = pickle.loads((folder / TASK_FILE).read_bytes())
    plan = json.loads((folder / PLAN_FILE).read_text(encoding="utf-8"))
    return task, ClusterConfig(**plan["cluster"])


def _remove_outputs(task: PredictTask, units: Sequence[Unit]) -> None:
    """Delete the joined files and the parts of ``units`` (``--overwrite``)."""
    from freipose.predict.merge import SHARD_RE

    names = {u.session for u in units}
    for s in names:
        session_output(task, s).unlink(missing_ok=True)
    for f in task.outdir.glob("*.poses.h5*"):
        m = SHARD_RE.match(f.name.removesuffix(".partial"))
        if m and m.group("session") in names:
            f.unlink()


def join_sessions(task: PredictTask, units: Sequence[Unit]) -> tuple[list[Path], dict[str, str]]:
    """Join the sessions whose units are all complete.

    A session that cannot be joined because its disk is full or read-only keeps its
    parts (a rerun joins it); the others are joined all the same.

    Returns:
        Every complete joined file, and session -> why it could not be joined.
    """
    from freipose.errors import OutputWriteError, filesystem_message
    from freipose.predict.merge import merge_outputs
    from freipose.predict.writer import is_complete

    out, unjoined = [], {}
    for s in task.sessions:
        target = session_output(task, s.name)
        mine = [u for u in units if u.session == s.name]
        if not (target.exists() and is_complete(target)):
            if not all(unit_is_done(task, u) for u in mine):
                continue
            try:
                merge_outputs([unit_output(task, u) for u in mine], task.outdir, remove=True)
            except OSError as exc:  # a full disk, a read-only folder (the lock, the file)
                why = str(exc) if isinstance(exc, OutputWriteError) else filesystem_message(exc)
                if why is None:
                    raise
                unjoined[s.name] = why
                continue
            journal(task.outdir, "joined", session=s.name, file=target, units=len(mine))
        out.append(target)
    return out, unjoined


def _failure_message(
    task: PredictTask, n_units: int, report: DriverReport, unjoined: dict[str, str]
) -> str:
    """The units that failed, the sessions not joined, and the command that finishes."""
    lines = [f"  {f.unit}: {f.reason} (after {f.attempts} jobs; log: {f.log or '-'})"
             for f in report.failed]  # fmt: skip
    lines += [f"  {s}: its units are done, its parts kept, but it was not joined: {why}"
              for s, why in unjoined.items()]  # fmt: skip
    heads = []
    if report.failed:
        heads.append(f"{len(report.failed)} of {n_units} units failed")
    if unjoined:
        heads.append(f"{len(unjoined)} of {len(task.sessions)} sessions could not be joined")
    return (
        "; ".join(heads)
        + "; the other units' outputs are kept:\n"
        + "\n".join(lines)
        + f"\nfix the cause and finish with `freipose jobs {task.outdir} --resume`"
    )


def run_predict(
    task: PredictTask,
    config: ClusterConfig,
    progress: bool = True,
    overwrite: bool = False,
    say: Callable[[str], None] = print,
) -> ClusterPredictResult:
    """Predict ``task``'s sessions unit by unit on the executor ``config`` names.

    Args:
        task: what to predict.
        config: the executor and its settings.
        progress: show a progress bar of the finished units.
        overwrite: predict every session again (its joined file and parts are removed).
        say: where the plan's summary goes.

    Raises:
        UnitsFailedError: units failed after their retries, or sessions could not be
            joined (the others' work is kept).
        OutputLockedError: another driver runs on the same output folder.
        ExecutorError: the engine cannot be used.
    """
    units = plan_units(task)
    with output_lock(task.outdir / JOBS_DIR / "driver", "job driver", option="-o"):
        if overwrite:
            _remove_outputs(task, units)
        _save_plan(task, config, units)
        executor = make_executor(config, task.outdir)
        say(f"{len(units)} units of at most {task.chunk_frames} frames over "
            f"{len(task.sessions)} sessions on the {config.executor} executor; status: "
            f"freipose jobs {task.outdir}")  # fmt: skip
        try:
            report = run_units(
                units, predict_unit, lambda u: UnitArg(task, u),
                lambda u: unit_is_done(task, u), executor, task.outdir,
                max_retries=config.max_retries, poll_s=config.poll_s, progress=progress,
            )  # fmt: skip
        finally:
            executor.close()
        joined, unjoined = join_sessions(task, units)
    if report.failed or unjoined:
        raise UnitsFailedError(_failure_message(task, len(units), report, unjoined))
    return ClusterPredictResult(report, tuple(joined), sum(u.frames for u in units))
