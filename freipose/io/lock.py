"""An exclusive lock on an output file, so that two runs never write into the same file.

A command that writes or resumes into an output holds :func:`output_lock` on it while it
works. The lock is a small JSON file ``<output>.lock`` next to the output, created
atomically; it names the owner (host, process id, start time, command line) so that a
refused run can say who holds it. A lock whose owner is known to be gone is *stale* and is
taken over:

* its host is this host and its process no longer runs, or
* it cannot be read or parsed and was last changed more than :data:`STALE_UNREADABLE_S`
  seconds ago (a run that died between creating the file and writing it).

A lock held by another host is never stale automatically (its process cannot be checked);
the refusal then says which file to delete if that run is gone.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shlex
import socket
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

from freipose.errors import FreiPoseError

log = logging.getLogger(__name__)

LOCK_SUFFIX = ".lock"
STALE_UNREADABLE_S = 60.0
_ATTEMPTS = 5


class OutputLockedError(FreiPoseError):
    """Another run holds the lock of the output that this run was asked to write.

    Attributes:
        owner: the run that holds it, as its lock file says (None: unreadable).
    """

    def __init__(self, message: str, owner: LockOwner | None = None):
        super().__init__(message)
        self.owner = owner


@dataclass(frozen=True)
class LockOwner:
    """The run that holds an output lock, as written in the lock file.

    Attributes:
        host: host name of the owner's machine.
        pid: the owner's process id on that host.
        started: when the owner took the lock (local time, ISO 8601).
        command: the owner's command line.
    """

    host: str
    pid: int
    started: str
    command: str

    def to_json(self) -> str:
        """The lock file's content."""
        return json.dumps(
            {"host": self.host, "pid": self.pid, "started": self.started, "command": self.command}
        )

    @classmethod
    def from_json(cls, text: str) -> LockOwner | None:
        """The owner written in ``text``; None when it is not a complete lock record."""
        try:
            d = json.loads(text)
            owner = cls(str(d["host"]), int(d["pid"]), str(d["started"]), str(d["command"]))
        except (ValueError, TypeError, KeyError):
            return None
        return owner if owner.host and owner.pid > 0 else None


def lock_path(path: str | Path) -> Path:
    """The lock file of the output ``path``: ``<path>.lock`` in the same folder."""
    path = Path(path)
    return path.with_name(path.name + LOCK_SUFFIX)


def _this_run() -> LockOwner:
    """The owner record of this process."""
    started = datetime.now().astimezone().isoformat(timespec="seconds")
    return LockOwner(socket.gethostname(), os.getpid(), started, shlex.join(sys.argv))


def _pid_runs(pid: int) -> bool:
    """Whether a process with id ``pid`` runs on this host (one of another user counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:  # e.g. a pid out of range: no such process
        return False
    return True


def _create(lock: Path, owner: LockOwner) -> bool:
    """Create ``lock`` with ``owner`` in it unless it exists; whether it was created."""
    try:
        fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
        return False
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(owner.to_json())
    except OSError as exc:  # e.g. a full disk: an empty lock would block the next run
        lock.unlink(missing_ok=True)
        raise OSError(exc.errno, exc.strerror, str(lock)) from exc
    return True


def _read(lock: Path) -> tuple[LockOwner | None, os.stat_result] | None:
    """The owner in ``lock`` (None if unreadable) and its stat; None when it is gone."""
    try:
        st = lock.stat()
        text = lock.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError):
        try:
            return None, lock.stat()
        except FileNotFoundError:
            return None
    return LockOwner.from_json(text), st


def _refusal(
    out: Path, lock: Path, owner: LockOwner | None, host: str, option: str = "-o"
) -> OutputLockedError:
    """The error for a lock held by ``owner`` (None: an unreadable lock file).

    ``option`` is the option of the refused command that names another output.
    """
    if owner is None:
        return OutputLockedError(
            f"another run (unknown: its lock file {lock} cannot be read) is writing {out}; "
            f"wait for it or pass another {option}; if that run is gone, delete {lock}"
        )
    msg = (
        f"another run ({owner.host}, pid {owner.pid}, started {owner.started}) is writing "
        f"{out}; wait for it or pass another {option}"
    )
    if owner.host != host:
        msg += f"; if that run is gone, delete {lock}"
    return OutputLockedError(msg, owner)


def _is_stale(owner: LockOwner | None, st: os.stat_result, host: str) -> bool:
    """Whether a lock with this owner (None: unreadable) and stat can be taken over."""
    if owner is None:
        return time.time() - st.st_mtime > STALE_UNREADABLE_S
    return owner.host == host and not _pid_runs(owner.pid)


def _remove_if_unchanged(lock: Path, st: os.stat_result) -> None:
    """Delete ``lock`` unless it was replaced since ``st`` was taken."""
    with contextlib.suppress(FileNotFoundError):
        now = lock.stat()
        if (now.st_ino, now.st_mtime_ns, now.st_size) == (st.st_ino, st.st_mtime_ns, st.st_size):
            lock.unlink()


def _acquire(out: Path, lock: Path, me: LockOwner, what: str, option: str = "-o") -> None:
    """Create ``lock`` for ``me``, taking over a stale one; raise if another run holds it."""
    for _ in range(_ATTEMPTS):
        if _create(lock, me):
            return
        found = _read(lock)
        if found is None:  # released between the two calls: try again
            continue
        owner, st = found
        if not _is_stale(owner, st, me.host):
            raise _refusal(out, lock, owner, me.host, option)
        who = "unreadable" if owner is None else f"of {owner.host}, pid {owner.pid}"
        log.warning("removed a stale lock (%s) of the %s %s", who, what, out)
        _remove_if_unchanged(lock, st)
    found = _read(lock)
    raise _refusal(out, lock, None if found is None else found[0], me.host, option)


def _release(lock: Path, me: LockOwner) -> None:
    """Delete ``lock`` if it still holds ``me`` (a lock taken over by another run stays)."""
    found = _read(lock)
    if found is not None and found[0] == me:
        with contextlib.suppress(FileNotFoundError):
            lock.unlink()


@contextlib.contextmanager
def output_lock(path: str | Path, what: str = "output", option: str = "-o") -> Iterator[Path]:
    """Hold the exclusive lock of the output ``path`` for the duration of the block.

    Creates ``<path>.lock`` (and the output's folder if needed) with this run's host, pid,
    start time and command line, and removes it when the block ends, also when it raises,
    unless another run has replaced it meanwhile. A stale lock (see the module docstring)
    is removed with a warning and taken.

    Args:
        path: the output file that the block writes or resumes into.
        what: what the output is (``"poses file"``, ``"checkpoint"``), for the log.
        option: the command's option that names another output (``-o``, ``--out``), for
            the refusal ("wait for it or pass another OPTION").

    Yields:
        The lock file's path.

    Raises:
        OutputLockedError: another run holds the lock.
    """
    out = Path(path)
    lock = lock_path(out)
    lock.parent.mkdir(parents=True, exist_ok=True)
    me = _this_run()
    _acquire(out, lock, me, what, option)
    try:
        yield lock
    finally:
        _release(lock, me)


__all__ = ["LOCK_SUFFIX", "LockOwner", "OutputLockedError", "lock_path", "output_lock"]
