"""Run a list of units on an executor until each is done or has failed too often.

A unit is *done* when its output on disk is complete (the driver asks ``is_done``; the
engine's word is not taken). A unit whose job ended without its output, because it raised
an error, was cancelled, ran out of time or its node died, is submitted again, at most
``max_retries`` times; then it is reported with the last reason and its log. Units whose
output is complete when the run starts are not submitted at all, so running the same
command again (or ``freipose jobs OUTDIR --resume``) submits exactly what is missing.

Every submission and every end is appended to the journal ``OUTDIR/.jobs/journal.jsonl``,
which ``freipose jobs`` reads.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from freipose.cluster.executors import ENDED, Executor, Ticket
from freipose.progress import progress_bar

log = logging.getLogger(__name__)

JOBS_DIR = ".jobs"
JOURNAL = "journal.jsonl"


@dataclass(frozen=True)
class Unit:
    """One piece of work: a session's frame chunk ``index`` of ``count``.

    Attributes:
        name: ``<session>.<index>-of-<count>``, as the status and the journal show it.
        session: the session's name.
        index: the chunk's index (0-based).
        count: the session's number of chunks.
        frames: the number of frames of the chunk.
    """

    name: str
    session: str
    index: int
    count: int
    frames: int


@dataclass(frozen=True)
class Failure:
    """A unit given up after its retries.

    Attributes:
        unit: the unit's name.
        reason: why its last job ended without its output.
        log: the last job's log file, where the engine keeps one.
        attempts: jobs it was given.
    """

    unit: str
    reason: str
    log: Path | None
    attempts: int


@dataclass(frozen=True)
class DriverReport:
    """What a run of the driver did.

    Attributes:
        done: names of the units whose output is complete.
        failed: the units given up.
        submitted: jobs submitted in this run (retries included).
        seconds: wall time.
    """

    done: tuple[str, ...]
    failed: tuple[Failure, ...]
    submitted: int
    seconds: float


def now_iso() -> str:
    """The current UTC time, ISO 8601 with seconds."""
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def journal(outdir: Path, event: str, **fields: Any) -> None:
    """Append one event to ``OUTDIR/.jobs/journal.jsonl`` (a line each, flushed at once)."""
    path = outdir / JOBS_DIR / JOURNAL
    path.parent.mkdir(parents=True, exist_ok=True)
    line = json.dumps({"time": now_iso(), "t": time.time(), "event": event, **fields}, default=str)
    with open(path, "a", encoding="utf-8") as f:
        f.write(line + "\n")
        f.flush()
        os.fsync(f.fileno())


def read_journal(outdir: Path) -> list[dict[str, Any]]:
    """The journal's events in order (a line cut by a crash is skipped)."""
    path = outdir / JOBS_DIR / JOURNAL
    if not path.is_file():
        return []
    events = []
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            events.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return events


def run_units(
    units: Sequence[Unit],
    fn: Callable[[Any], Any],
    arg_of: Callable[[Unit], Any],
    is_done: Callable[[Unit], bool],
    executor: Executor,
    outdir: Path,
    *,
    max_retries: int,
    poll_s: float,
    progress: bool = True,
) -> DriverReport:
    """Run ``fn(arg_of(unit))`` on ``executor`` for every unit that is not done yet.

    Args:
        units: every unit of the job (done ones are skipped).
        fn: the unit's work (module level, picklable).
        arg_of: the unit's argument of ``fn``.
        is_done: whether a unit's output is complete.
        executor: the engine.
        outdir: the output folder (the journal goes under ``OUTDIR/.jobs``).
        max_retries: further jobs a unit gets after its first one ended without output.
        poll_s: seconds between two looks at the engine.
        progress: show a progress bar of the finished units.

    Returns:
        A :class:`DriverReport`.
    """
    t0 = time.perf_counter()
    by_name = {u.name: u for u in units}
    to_submit = [u for u in units if not is_done(u)]
    active: dict[str, Ticket] = {}
    attempts = dict.fromkeys(by_name, 0)
    failed: list[Failure] = []
    submitted = 0
    bar = progress_bar(total=len(units), initial=len(units) - len(to_submit), unit="unit",
                       desc=f"units ({executor.name})", disable=not progress or None)  # fmt: skip
    with bar:
        while to_submit or active:
            if to_submit:
                tickets = executor.submit(fn, [arg_of(u) for u in to_submit],
                                          [u.name for u in to_submit])  # fmt: skip
                for t in tickets:
                    attempts[t.unit] += 1
                    active[t.unit] = t
                    journal(outdir, "submitted", unit=t.unit, job_id=t.job_id, log=t.log,
                            attempt=attempts[t.unit], executor=executor.name)  # fmt: skip
                submitted += len(tickets)
                to_submit = []
            executor.wait(list(active.values()), poll_s)
            states = executor.states(list(active.values()))
            for name, t in list(active.items()):
                st = states[t.job_id]
                if st.state != ENDED:
                    continue
                del active[name]
                unit = by_name[name]
                if is_done(unit):
                    journal(outdir, "done", unit=name, job_id=t.job_id)
                    bar.update(1)
                    continue
                reason = st.reason or "the job ended without writing the unit's output"
                journal(outdir, "failed", unit=name, job_id=t.job_id, reason=reason, log=t.log)
                if attempts[name] <= max_retries:
                    log.warning("unit %s (job %s) ended without its output: %s; submitting it "
                                "again (attempt %d of %d)", name, t.job_id, reason,
                                attempts[name] + 1, max_retries + 1)  # fmt: skip
                    to_submit.append(unit)
                else:
                    failed.append(Failure(name, reason, t.log, attempts[name]))
    done = tuple(u.name for u in units if is_done(u))
    return DriverReport(done, tuple(failed), submitted, time.perf_counter() - t0)
