"""One way to run any stage as units on an executor: the plan, the units' jobs, the join.

A stage (``predict``, ``detect``, ``smooth``, ``analyze variables``, ``render``) describes its
work as a :class:`StageTask`: a picklable value that plans its units, runs one unit (in a
worker process or a SLURM job), says whether a unit's output is complete on disk, and joins
the parts of an output whose units are all complete. :func:`run_stage` does the rest for
every stage alike: it saves the plan (``.jobs/plan.json`` and the pickled task, which
``freipose jobs --resume`` runs again), submits the units that are not done through the
driver (:func:`freipose.cluster.driver.run_units`: bounded retries, then a report by
name), joins what can be joined, and reports what failed with the command that finishes.

Each job's state lives in the ``.jobs`` folder of its *root*: the output folder of a stage
that writes a folder (``predict -o OUTDIR``, ``smooth -o OUTDIR``), or
``<folder>/.jobs/<name>`` for a stage that writes one file ``<folder>/<name>``
(``detect``, ``render``, ``analyze variables``; see :func:`file_job_root`).
"""

from __future__ import annotations

import dataclasses
import json
import os
import pickle
import signal
import socket
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Protocol

from freipose.cluster.config import ClusterConfig
from freipose.cluster.driver import JOBS_DIR, DriverReport, Unit, journal, now_iso, run_units
from freipose.cluster.executors import Executor, LocalExecutor, SlurmExecutor
from freipose.errors import FreiPoseError
from freipose.io.atomic import atomic_path, atomic_write_text
from freipose.io.lock import output_lock

TASK_FILE = "task.pkl"
PLAN_FILE = "plan.json"
UNITS_DIR = "units"


class UnitStopped(Exception):
    """SLURM ended the unit's job (cancelled, preempted, out of time): its part stays resumable."""


class UnitsFailedError(FreiPoseError):
    """Some units failed after their retries; the message names them and how to finish."""


class StageTask(Protocol):
    """A stage's work as units (a frozen dataclass, pickled into every job).

    Attributes:
        command: the command's name (``"predict"``, ``"detect"``...), shown by ``freipose jobs``.
        noun: what an output is (``"session"``, ``"file"``), for the plan's summary.
        root: the folder whose ``.jobs`` holds the job's plan, journal and unit records.
        target: the path to give ``freipose jobs`` (the output folder or file).
        uses_torch: whether a unit runs PyTorch (its threads are set before the unit starts).
        threads: PyTorch and OpenCV threads of each unit.
    """

    command: ClassVar[str]
    noun: ClassVar[str]
    uses_torch: ClassVar[bool]

    @property
    def root(self) -> Path:
        """The folder whose ``.jobs`` holds the job."""

    @property
    def target(self) -> Path:
        """The path to give ``freipose jobs``."""

    @property
    def threads(self) -> int:
        """Threads of each unit."""

    def plan_units(self) -> list[Unit]:
        """Every unit of the job; ``unit.session`` names the output the unit belongs to."""

    def run_unit(self, unit: Unit, on_first: Callable[[], None]) -> None:
        """Do one unit's work; call ``on_first`` when its frames start (the overhead's end).

        ``predict`` calls it when its first batch is done, the other stages when their
        inputs are open and the work on the frames begins.
        """

    def unit_is_done(self, unit: Unit) -> bool:
        """Whether the unit's part, or the output it belongs to, is complete on disk."""

    def output(self, group: str) -> Path:
        """The output file of ``group`` (a ``unit.session``)."""

    def output_done(self, group: str) -> bool:
        """Whether the output of ``group`` is complete."""

    def join(self, group: str, units: Sequence[Unit]) -> None:
        """Join the complete parts of ``group`` into its output, check it, remove the parts.

        Raises:
            OSError: the output cannot be written (a full disk, a read-only folder).
        """

    def remove_outputs(self, units: Sequence[Unit]) -> None:
        """Delete the outputs and parts of ``units`` (``--overwrite``)."""


def file_job_root(output: Path) -> Path:
    """The root of the job that writes the single file ``output``: ``<folder>/.jobs/<name>``."""
    output = Path(output)
    return output.parent / JOBS_DIR / output.name


class FolderJob:
    """A stage whose job lives in its output folder ``self.outdir`` (``OUTDIR/.jobs``)."""

    @property
    def root(self) -> Path:
        """The output folder."""
        return self.outdir  # type: ignore[attr-defined]

    @property
    def target(self) -> Path:
        """``freipose jobs OUTDIR``."""
        return self.outdir  # type: ignore[attr-defined]


class FileJob:
    """A stage that writes one file ``self.out_path``; its job is in ``<folder>/.jobs/<name>``."""

    @property
    def root(self) -> Path:
        """``<folder>/.jobs/<name>`` of the output file."""
        return file_job_root(self.out_path)  # type: ignore[attr-defined]

    @property
    def target(self) -> Path:
        """``freipose jobs OUTPUT``."""
        return self.out_path  # type: ignore[attr-defined]


def has_plan(root: Path) -> bool:
    """Whether ``root`` holds a stage job's plan."""
    return (Path(root) / JOBS_DIR / PLAN_FILE).is_file() and (
        Path(root) / JOBS_DIR / TASK_FILE
    ).is_file()


def find_job_roots(path: Path) -> list[Path]:
    """The roots of the stage jobs that ``path`` names.

    ``path`` is an output folder (its own job, and the jobs of the single files written
    into it) or a single output file (whether it exists yet or not).
    """
    path = Path(path)
    roots = []
    if has_plan(path):
        roots.append(path)
    if (path / JOBS_DIR).is_dir():
        roots += sorted(p for p in (path / JOBS_DIR).iterdir() if p.is_dir() and has_plan(p))
    if not path.is_dir() and has_plan(file_job_root(path)):
        roots.append(file_job_root(path))
    return roots


def unit_record(root: Path, unit: Unit, **fields: Any) -> None:
    """Write what a unit is doing to ``ROOT/.jobs/units/<unit>.json`` (for the status)."""
    path = Path(root) / JOBS_DIR / UNITS_DIR / f"{unit.name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps({"unit": unit.name, **fields}, indent=1))


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


def _use_threads(n: int, torch: bool) -> None:
    """``n`` OpenCV threads, and ``n`` PyTorch threads where the unit uses PyTorch."""
    import cv2

    cv2.setNumThreads(n)
    if torch:
        import torch as pytorch

        pytorch.set_num_threads(n)


@dataclass(frozen=True)
class UnitArg:
    """One unit's argument: the task and which unit.

    Attributes:
        task: the stage's task.
        unit: the unit.
    """

    task: Any
    unit: Unit


def run_unit(arg: UnitArg) -> int:
    """Run one unit (in a worker process or a SLURM job); returns its frames."""
    task, unit = arg.task, arg.unit
    _stop_on_sigterm()
    _use_threads(task.threads, task.uses_torch)
    job = os.environ.get("SLURM_ARRAY_JOB_ID", os.environ.get("SLURM_JOB_ID", ""))
    if job and "SLURM_ARRAY_TASK_ID" in os.environ:
        job = f"{job}_{os.environ['SLURM_ARRAY_TASK_ID']}"
    where: dict[str, Any] = {"host": socket.gethostname(), "pid": os.getpid(), "job_id": job}
    t0 = time.perf_counter()
    first: list[float] = []
    where["started_at"] = time.time()
    unit_record(task.root, unit, state="running", started=now_iso(), **where)

    def on_first() -> None:
        if not first:
            first.append(time.time())

    task.run_unit(unit, on_first)
    seconds = time.perf_counter() - t0
    unit_record(task.root, unit, state="done", finished=now_iso(), seconds=round(seconds, 3),
                first_frame_at=first[0] if first else None, frames=unit.frames,
                **where)  # fmt: skip
    return unit.frames


@dataclass(frozen=True)
class StageResult:
    """What a stage run through an executor did.

    Attributes:
        report: the driver's report.
        joined: the complete outputs (joined from parts, written by a unit, or earlier).
        frames: frames of all units.
    """

    report: DriverReport
    joined: tuple[Path, ...]
    frames: int


def make_executor(config: ClusterConfig, root: Path) -> Executor:
    """The engine ``config.executor`` names (its SLURM logs go under ``ROOT/.jobs/slurm``)."""
    if config.executor == "slurm":
        return SlurmExecutor(config, Path(root) / JOBS_DIR / "slurm")
    return LocalExecutor(config)


def groups(units: Sequence[Unit]) -> dict[str, list[Unit]]:
    """Output (``unit.session``) -> its units, in the units' order."""
    out: dict[str, list[Unit]] = {}
    for u in units:
        out.setdefault(u.session, []).append(u)
    return out


def save_plan(task: StageTask, config: ClusterConfig, units: Sequence[Unit]) -> None:
    """``ROOT/.jobs/plan.json`` (read by ``freipose jobs``) and the task for ``--resume``."""
    folder = task.root / JOBS_DIR
    folder.mkdir(parents=True, exist_ok=True)
    doc = {
        "command": task.command,
        "created": now_iso(),
        "target": str(task.target),
        "cluster": dataclasses.asdict(config),
        "sessions": list(groups(units)),
        "units": [dataclasses.asdict(u) for u in units],
    }
    atomic_write_text(folder / PLAN_FILE, json.dumps(doc, indent=1, default=str))
    with atomic_path(folder / TASK_FILE) as tmp:
        tmp.write_bytes(pickle.dumps(task))


def load_task(root: Path) -> tuple[Any, ClusterConfig]:
    """The task and cluster settings saved by an earlier run into ``root``.

    Raises:
        FreiPoseError: ``root`` holds no job of a command run with ``--executor``.
    """
    folder = Path(root) / JOBS_DIR
    if not has_plan(Path(root)):
        raise FreiPoseError(
            f"{root}: no job found (no {JOBS_DIR}/{PLAN_FILE}); it is written by "
            "`freipose predict|detect|smooth|render|analyze variables ... --executor local|slurm`"
        )
    task = pickle.loads((folder / TASK_FILE).read_bytes())
    plan = json.loads((folder / PLAN_FILE).read_text(encoding="utf-8"))
    return task, ClusterConfig(**plan["cluster"])


def _refuse_other_command(task: StageTask) -> None:
    """Refuse to put a job where another command's job is (one job per output folder).

    Raises:
        FreiPoseError: ``ROOT/.jobs`` holds the job of another command.
    """
    path = task.root / JOBS_DIR / PLAN_FILE
    try:
        other = json.loads(path.read_text(encoding="utf-8")).get("command", task.command)
    except (OSError, ValueError):
        return
    if other != task.command:
        raise FreiPoseError(
            f"{task.root} holds the job of `freipose {other}` ({path}); write the output of "
            f"`freipose {task.command}` to another folder"
        )


def join_outputs(task: StageTask, units: Sequence[Unit]) -> tuple[list[Path], dict[str, str]]:
    """Join the outputs whose units are all complete.

    An output that cannot be joined because its disk is full or read-only keeps its parts
    (a rerun joins it); the others are joined all the same.

    Returns:
        Every complete output, and output (``unit.session``) -> why it could not be joined.
    """
    from freipose.errors import OutputWriteError, filesystem_message

    out, unjoined = [], {}
    for group, mine in groups(units).items():
        if not task.output_done(group):
            if not all(task.unit_is_done(u) for u in mine):
                continue
            try:
                task.join(group, mine)
            except OSError as exc:  # a full disk, a read-only folder (the lock, the file)
                why = str(exc) if isinstance(exc, OutputWriteError) else filesystem_message(exc)
                if why is None:
                    raise
                unjoined[group] = why
                continue
            journal(task.root, "joined", session=group, file=task.output(group), units=len(mine))
        out.append(task.output(group))
    return out, unjoined


def failure_message(
    task: StageTask, n_units: int, report: DriverReport, unjoined: dict[str, str]
) -> str:
    """The units that failed, the outputs not joined, and the command that finishes."""
    lines = [f"  {f.unit}: {f.reason} (after {f.attempts} jobs; log: {f.log or '-'})"
             for f in report.failed]  # fmt: skip
    lines += [f"  {s}: its units are done, its parts kept, but it was not joined: {why}"
              for s, why in unjoined.items()]  # fmt: skip
    heads = []
    if report.failed:
        heads.append(f"{len(report.failed)} of {n_units} units failed")
    if unjoined:
        n = len(groups(task.plan_units()))
        heads.append(f"{len(unjoined)} of {n} {task.noun}s could not be joined")
    return (
        "; ".join(heads)
        + "; the other units' outputs are kept:\n"
        + "\n".join(lines)
        + f"\nfix the cause and finish with `freipose jobs {task.target} --resume`"
    )


def run_stage(
    task: StageTask,
    config: ClusterConfig,
    progress: bool = True,
    overwrite: bool = False,
    say: Callable[[str], None] = print,
) -> StageResult:
    """Run ``task``'s units on the executor ``config`` names and join its outputs.

    Args:
        task: the stage's work.
        config: the executor and its settings.
        progress: show a progress bar of the finished units.
        overwrite: do every unit again (the outputs and parts are removed first).
        say: where the plan's summary goes.

    Raises:
        UnitsFailedError: units failed after their retries, or outputs could not be
            joined (the others' work is kept).
        OutputLockedError: another driver runs on the same job.
        ExecutorError: the engine cannot be used.
    """
    units = task.plan_units()
    with output_lock(task.root / JOBS_DIR / "driver", "job driver", option="-o"):
        _refuse_other_command(task)
        if overwrite:
            task.remove_outputs(units)
        save_plan(task, config, units)
        executor = make_executor(config, task.root)
        n_groups = len(groups(units))
        say(f"{len(units)} units ({sum(u.frames for u in units)} frames) of {n_groups} "
            f"{task.noun}{'s' if n_groups != 1 else ''} on the {config.executor} executor; "
            f"status: freipose jobs {task.target}")  # fmt: skip
        try:
            report = run_units(
                units, run_unit, lambda u: UnitArg(task, u), task.unit_is_done, executor,
                task.root, max_retries=config.max_retries, poll_s=config.poll_s,
                progress=progress,
            )  # fmt: skip
        finally:
            executor.close()
        joined, unjoined = join_outputs(task, units)
    if report.failed or unjoined:
        raise UnitsFailedError(failure_message(task, len(units), report, unjoined))
    return StageResult(report, tuple(joined), sum(u.frames for u in units))


class WholeOutputs:
    """The units of a stage that writes each output whole, one unit per output.

    Smoothing runs forward and backward over a whole recording, the variables' filters and
    STFTs over a whole poses file, and an overlay video is one encoded stream: a unit
    writes its output in one go (under its lock, under a temporary name), so there are no
    parts to join. A subclass lists its outputs in :meth:`outputs` and does the work in
    ``run_unit``.
    """

    def outputs(self) -> dict[str, tuple[Path, int]]:
        """Output name -> (the file a unit writes, its frames)."""
        raise NotImplementedError

    def plan_units(self) -> list[Unit]:
        """One unit per output."""
        return [Unit(name, name, 0, 1, frames) for name, (_, frames) in self.outputs().items()]

    def output(self, group: str) -> Path:
        """The file of output ``group``."""
        return self.outputs()[group][0]

    def output_done(self, group: str) -> bool:
        """Whether the file exists (it is only ever written whole)."""
        return self.output(group).is_file()

    def unit_is_done(self, unit: Unit) -> bool:
        """Whether the unit's output exists."""
        return self.output_done(unit.session)

    def join(self, group: str, units: Sequence[Unit]) -> None:
        """Nothing to join: the unit wrote the output whole."""

    def remove_outputs(self, units: Sequence[Unit]) -> None:
        """Delete the units' outputs."""
        for u in units:
            self.output(u.session).unlink(missing_ok=True)


def poses_frames(path: Path) -> int:
    """The frames of a poses file (0 where its header cannot tell: the unit will say why)."""
    from freipose.io.poses import run_state

    try:
        return run_state(path).total
    except (OSError, FreiPoseError):
        return 0
