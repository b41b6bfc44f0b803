"""``freipose predict --executor ...``: sessions split into frame chunks run as units.

Each session's frames are cut into units of ``chunk_frames`` frames (whole batches, counted
from the start of the run's frame range); a unit is the prediction's shard primitive
(``--shard I/N``), so it writes ``OUTDIR/<session>.shard-I-of-N.poses.h5`` under that file's
lock, resumes a part written before it was killed, and is complete when the file says so.
Its batches are the batches of a single run over the whole session, so, with the same
number of threads per process, the units' joined file equals a single run's output value
for value. When every unit of a session is complete the driver
(:func:`freipose.cluster.stages.run_stage`) joins them into ``OUTDIR/<session>.poses.h5``,
checks that every frame is there exactly once, and removes the parts.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from freipose.cluster.config import ClusterConfig
from freipose.cluster.driver import Unit
from freipose.cluster.stages import (
    PLAN_FILE,
    TASK_FILE,
    FolderJob,
    StageResult,
    UnitArg,
    UnitsFailedError,
    UnitStopped,
    join_outputs,
    make_executor,
    run_stage,
    run_unit,
)
from freipose.io.session import Session
from freipose.io.video import frame_range

__all__ = [
    "PLAN_FILE",
    "TASK_FILE",
    "ClusterPredictResult",
    "PredictTask",
    "UnitArg",
    "UnitStopped",
    "UnitsFailedError",
    "join_sessions",
    "load_task",
    "make_executor",
    "plan_units",
    "predict_unit",
    "run_predict",
    "unit_is_done",
]

#: What ``predict`` through an executor did (the stages' common result).
ClusterPredictResult = StageResult

#: A unit's work in its worker process or SLURM job (the stages' common entry point).
predict_unit = run_unit


@dataclass(frozen=True)
class PredictTask(FolderJob):
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

    command: ClassVar[str] = "predict"
    noun: ClassVar[str] = "session"
    uses_torch: ClassVar[bool] = True

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

    def plan_units(self) -> list[Unit]:
        """Every session cut into whole-batch chunks of its frames."""
        from freipose.predict.run import commit_rows

        rows = commit_rows(self.batch_size, self.chunk_frames)
        units = []
        for s in self.sessions:
            r = frame_range(self.frames, s.num_frames)
            n = max(1, math.ceil((r.stop - r.start) / rows))
            for i in range(n):
                a, b = r.start + i * rows, min(r.start + (i + 1) * rows, r.stop)
                units.append(Unit(f"{s.name}.{i}-of-{n}", s.name, i, n, b - a))
        return units

    def unit_output(self, unit: Unit) -> Path:
        """The part unit ``unit`` writes."""
        from freipose.predict.run import output_path

        return output_path(self.outdir, unit.session, (unit.index, unit.count))

    def output(self, group: str) -> Path:
        """The joined file of a session."""
        from freipose.predict.run import output_path

        return output_path(self.outdir, group)

    def output_done(self, group: str) -> bool:
        """Whether the session's joined file is complete."""
        from freipose.predict.writer import is_complete

        joined = self.output(group)
        return joined.exists() and is_complete(joined)

    def unit_is_done(self, unit: Unit) -> bool:
        """Whether the unit's part is complete (or its session's joined file already is)."""
        from freipose.predict.writer import is_complete

        part = self.unit_output(unit)
        return self.output_done(unit.session) or (part.exists() and is_complete(part))

    def run_unit(self, unit: Unit, on_first: Callable[[], None]) -> None:
        """Predict the unit's shard of its session."""
        from freipose.predict.network import predict_sessions

        predict_sessions(
            [self.session(unit.session)], self.model, self.spec, self.outdir,
            frames=self.frames, batch_size=self.batch_size, device=self.device,
            refine=self.refine, overrides=self.overrides, shard=(unit.index, unit.count),
            chunk_frames=self.chunk_frames, expected_skeleton=self.skeleton, progress=False,
            on_batch=lambda n: on_first(),
        )  # fmt: skip

    def join(self, group: str, units: Sequence[Unit]) -> None:
        """Merge the session's parts (every frame exactly once) and remove them."""
        from freipose.predict.merge import merge_outputs

        merge_outputs([self.unit_output(u) for u in units], self.outdir, remove=True)

    def remove_outputs(self, units: Sequence[Unit]) -> None:
        """Delete the joined files and the parts of ``units``' sessions."""
        from freipose.predict.merge import SHARD_RE

        names = {u.session for u in units}
        for s in names:
            self.output(s).unlink(missing_ok=True)
        for f in self.outdir.glob("*.poses.h5*"):
            m = SHARD_RE.match(f.name.removesuffix(".partial"))
            if m and m.group("session") in names:
                f.unlink()


def plan_units(task: PredictTask) -> list[Unit]:
    """The units of ``task``: every session cut into whole-batch chunks of its frames."""
    return task.plan_units()


def unit_is_done(task: PredictTask, unit: Unit) -> bool:
    """Whether the unit's part is complete (or its session's joined file already is)."""
    return task.unit_is_done(unit)


def join_sessions(task: PredictTask, units: Sequence[Unit]) -> tuple[list[Path], dict[str, str]]:
    """Join the sessions whose units are all complete (see :func:`.stages.join_outputs`)."""
    return join_outputs(task, units)


def load_task(outdir: Path) -> tuple[PredictTask, ClusterConfig]:
    """The task and cluster settings saved by an earlier run into ``OUTDIR``."""
    from freipose.cluster.stages import load_task as load

    return load(outdir)


def run_predict(
    task: PredictTask,
    config: ClusterConfig,
    progress: bool = True,
    overwrite: bool = False,
    say: Callable[[str], None] = print,
) -> StageResult:
    """Predict ``task``'s sessions unit by unit on the executor ``config`` names.

    See :func:`freipose.cluster.stages.run_stage` (what it raises, what it returns).
    """
    return run_stage(task, config, progress=progress, overwrite=overwrite, say=say)
