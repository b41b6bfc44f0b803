"""The state of every unit of a job of any stage, from its files, its journal and the scheduler.

A unit is ``done`` when its part (or the output it belongs to) is complete on disk;
``running`` or ``queued`` while the executor lists its last job so (SLURM: ``squeue``;
the local executor's jobs are running while their driver runs); ``failed`` when its last
job ended without the part; ``waiting`` when it never had a job.
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

from freipose.cluster.driver import JOBS_DIR, read_journal
from freipose.cluster.executors import squeue_states
from freipose.cluster.stages import load_task

DONE, RUNNING, QUEUED, FAILED, WAITING = "done", "running", "queued", "failed", "waiting"


@dataclass(frozen=True)
class UnitStatus:
    """One unit's state.

    Attributes:
        unit: its name.
        session: its session.
        frames: its frames.
        state: ``done``, ``running``, ``queued``, ``failed`` or ``waiting``.
        job_id: its last job ('' before any).
        attempts: jobs it was given.
        reason: the scheduler's state or reason, or the unit's error.
        log: its last job's log file.
        seconds: how long its finished job ran (None: unknown or unfinished).
    """

    unit: str
    session: str
    frames: int
    state: str
    job_id: str = ""
    attempts: int = 0
    reason: str = ""
    log: str = ""
    seconds: float | None = None


@dataclass(frozen=True)
class JobsStatus:
    """Every unit of the job in ``outdir`` and the throughput so far.

    Attributes:
        outdir: the job's root (the folder whose ``.jobs`` holds it).
        executor: the executor the job ran on.
        units: the units' states.
        frames_per_s: done frames per second of wall time since the first submission
            (None before any).
        command: the stage (``predict``, ``detect``...).
        target: what ``freipose jobs`` takes for this job: the output folder, or the output
            file of a command that writes one (None: not known, the root is shown).
        unjoined: the outputs whose units are all done but whose joined file is not there
            (not joined yet, or the join failed: a full disk).
    """

    outdir: Path
    executor: str
    units: tuple[UnitStatus, ...]
    frames_per_s: float | None
    command: str = "predict"
    target: Path | None = None
    unjoined: tuple[str, ...] = ()

    def counts(self) -> dict[str, int]:
        """State -> number of units."""
        return dict(Counter(u.state for u in self.units))

    def missing(self) -> list[UnitStatus]:
        """The units that are not done."""
        return [u for u in self.units if u.state != DONE]


def _unit_seconds(outdir: Path, unit: str) -> float | None:
    path = outdir / JOBS_DIR / "units" / f"{unit}.json"
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return None
    return doc.get("seconds")


def _last_jobs(events: Sequence[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Unit -> its last submission (with ``attempts`` and the last failure's reason)."""
    last: dict[str, dict[str, Any]] = {}
    for e in events:
        unit = e.get("unit")
        if unit is None:
            continue
        if e["event"] == "submitted":
            n = last.get(unit, {}).get("attempts", 0) + 1
            last[unit] = {**e, "attempts": n, "ended": False}
        elif (
            e["event"] in ("failed", "done")
            and unit in last
            and e.get("job_id") == last[unit].get("job_id")
        ):
            last[unit].update(ended=True, reason=e.get("reason", ""))
    return last


def _throughput(events: Sequence[dict[str, Any]], frames_done: int) -> float | None:
    times = [datetime.fromisoformat(e["time"]) for e in events if "time" in e]
    if not times or frames_done == 0:
        return None
    span = (max(times) - min(times)).total_seconds()
    return frames_done / span if span > 0 else None


def jobs_status(outdir: str | Path) -> JobsStatus:
    """The state of every unit of the job whose root is ``outdir``.

    Raises:
        FreiPoseError: ``outdir`` holds no job.
    """
    outdir = Path(outdir)
    task, config = load_task(outdir)
    units = task.plan_units()
    events = read_journal(outdir)
    last = _last_jobs(events)
    open_ids = [v["job_id"] for v in last.values() if not v["ended"]]
    listed = squeue_states(open_ids) if config.executor == "slurm" else None
    out = []
    for u in units:
        job = last.get(u.name, {})
        common = {"job_id": job.get("job_id", ""), "attempts": job.get("attempts", 0),
                  "log": str(job.get("log") or "")}  # fmt: skip
        if task.unit_is_done(u):
            state, reason = DONE, ""
        elif not job:
            state, reason = WAITING, ""
        elif listed is not None and job["job_id"] in listed:
            js = listed[job["job_id"]]
            state, reason = (RUNNING if js.state == "running" else QUEUED), js.reason
        elif job["ended"] or listed is not None:
            state, reason = FAILED, job.get("reason") or "ended without its output"
        else:  # a local job whose driver may still run: its unit record says more
            state, reason = QUEUED, ""
        out.append(UnitStatus(u.name, u.session, u.frames, state, reason=reason,
                              seconds=_unit_seconds(outdir, u.name), **common))  # fmt: skip
    done_frames = sum(u.frames for u in out if u.state == DONE)
    by_group: dict[str, list[UnitStatus]] = {}
    for st in out:
        by_group.setdefault(st.session, []).append(st)
    unjoined = tuple(g for g, us in by_group.items()
                     if all(u.state == DONE for u in us) and not task.output_done(g))  # fmt: skip
    return JobsStatus(outdir, config.executor, tuple(out), _throughput(events, done_frames),
                      task.command, task.target, unjoined)  # fmt: skip
