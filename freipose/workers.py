"""Worker processes: one way to start a process pool and one runner for lists of jobs.

:func:`process_pool` starts workers from a clean forkserver process where the platform has
one (forking a process whose OpenCV or FFmpeg thread pools are running can deadlock the
child), with the given modules imported once in the server so that every worker forks
ready to run; elsewhere the workers are spawned. :func:`run_jobs` maps a function over a
list of jobs in such a pool, or in this process when one worker is asked for.

The forkserver process is started with ``python -c``, so on Python 3.11 the working folder
comes first on its ``sys.path`` (the parent's ``sys.path`` is handed to the workers, not to
the server). A folder or module in the working folder named like a preloaded package (a
folder ``freipose``, say, holding a clone of this repository, or an empty one) would then
be imported in the server instead of the installed package, and every worker forked from
it would inherit that module. :func:`pool_context` therefore preloads only the modules
that the working folder does not shadow; the others are imported by each worker itself,
after it has taken over the parent's ``sys.path``. :func:`worker_errors` turns a pool whose
worker died into a one-line :class:`WorkerError`.

A worker blocks on its job queue, whose pipe it holds both ends of, and the forkserver and
the resource tracker stay up while any worker does: a parent killed with SIGKILL would leave
them all running. The workers of :func:`process_pool` and the server of :func:`start_manager`
therefore watch the process that started them (:func:`die_with`) and end with it; the
forkserver and the resource tracker then see their pipes close and end too.

:func:`choose_threads` picks the number of compute threads (PyTorch, OpenCV) from the cores
that other processes leave free: on a 2-core machine where another process keeps one core
busy, two PyTorch threads run several times slower than one. :func:`keep_freed_memory` makes
glibc's allocator reuse the memory of freed tensors instead of handing it back to the system
and faulting it in afresh at the next step.
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib.util
import logging
import multiprocessing as mp
import os
import select
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from functools import partial
from importlib.machinery import ModuleSpec, PathFinder
from multiprocessing.context import BaseContext
from multiprocessing.managers import SyncManager
from pathlib import Path
from typing import Any, TypeVar

from freipose.errors import FreiPoseError
from freipose.progress import progress_bar

log = logging.getLogger(__name__)

J = TypeVar("J")
R = TypeVar("R")

START_METHODS = ("forkserver", "spawn")


class WorkerError(FreiPoseError):
    """A worker process died before it could report its error."""


def cpu_cores() -> int:
    """The number of cores this process may run on (its CPU affinity, else all)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _cpu_times(cpus: set[int]) -> tuple[float, float] | None:
    """(busy, total) jiffies of the given CPUs from ``/proc/stat`` (None where unreadable)."""
    try:
        lines = Path("/proc/stat").read_text().splitlines()
    except OSError:
        return None
    busy = total = 0.0
    for ln in lines:
        name, _, rest = ln.partition(" ")
        if name.startswith("cpu") and name[3:].isdigit() and int(name[3:]) in cpus:
            v = [float(x) for x in rest.split()]
            idle = v[3] + (v[4] if len(v) > 4 else 0.0)  # idle + iowait
            total += sum(v[:8])
            busy += sum(v[:8]) - idle
    return (busy, total) if total > 0 else None


def other_load(window: float = 0.5) -> float:
    """How many cores other processes keep busy, in cores (0 on an idle machine).

    On Linux the share of busy time of this process's cores over ``window`` seconds
    (while this process sleeps, its own CPU time subtracted); elsewhere the 1-minute load
    average minus this process's thread.
    """
    try:
        cpus = os.sched_getaffinity(0)
    except (AttributeError, OSError):
        cpus = set()
    before, own0 = _cpu_times(cpus), time.process_time()
    if before is not None:
        time.sleep(window)
        after, own = _cpu_times(cpus), time.process_time() - own0
        if after is not None and after[1] > before[1]:
            share = (after[0] - before[0]) / (after[1] - before[1])
            return max(0.0, share * len(cpus) - own / window)
    try:
        return max(0.0, os.getloadavg()[0] - 1.0)
    except (AttributeError, OSError):
        return 0.0


# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4


def keep_freed_memory() -> bool:
    """Make glibc's allocator keep freed memory in the process for reuse.

    By default glibc serves every block above a threshold (at most 32 MB) with a fresh
    ``mmap`` and unmaps it when freed, and returns the heap's free top to the system; a
    network step that allocates and frees the same large tensors again and again then
    spends its time in page faults that zero new pages. With ``mmap`` off and the trim
    threshold at 1 GB freed blocks stay in the heap and later steps reuse them; the process
    holds on to its peak memory instead of returning it between steps. Elsewhere than Linux
    with glibc nothing changes.

    Returns:
        True where the allocator took the settings.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (e.g. musl)
        return False
    return bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, 1 << 30))


def choose_threads(requested: int | None, workers: int = 1) -> int:
    """The number of compute threads (PyTorch, OpenCV) for each of ``workers`` processes.

    An explicit ``requested`` count wins, then an ``OMP_NUM_THREADS`` set in the
    environment; otherwise the cores this process may use minus those other processes
    keep busy (:func:`other_load`, rounded), divided by ``workers``, at least 1. The
    choice is logged at INFO, e.g. ``using 1 PyTorch thread (2 cores, load 1.3)``.

    Args:
        requested: the user's count (``--threads``), or None to choose.
        workers: processes that each run that many threads.

    Returns:
        The thread count (>= 1).

    Raises:
        FreiPoseError: ``requested`` or ``OMP_NUM_THREADS`` is below 1 or not a number.
    """
    if requested is not None:
        if requested < 1:
            raise FreiPoseError(f"--threads must be at least 1, got {requested}")
        n, why = int(requested), "--threads"
    elif os.environ.get("OMP_NUM_THREADS", "").strip():
        env = os.environ["OMP_NUM_THREADS"].strip()
        if not env.isdigit() or int(env) < 1:
            raise FreiPoseError(
                f"OMP_NUM_THREADS must be a whole number of at least 1, got {env!r}; unset it "
                "or pass --threads N"
            )
        n, why = int(env), "OMP_NUM_THREADS"
    else:
        cores, load = cpu_cores(), other_load()
        n = max(1, (cores - int(round(load))) // max(1, workers))
        why = f"{cores} cores, load {load:.1f}" + (f", {workers} workers" if workers > 1 else "")
    log.info("using %d PyTorch thread%s (%s)", n, "" if n == 1 else "s", why)
    return n


def _spec_location(spec: ModuleSpec | None) -> tuple[str, ...]:
    """Where a module spec's code lives: its file, else its package folders (resolved)."""
    if spec is None:
        return ()
    if spec.origin is not None and spec.has_location:
        return (os.path.realpath(spec.origin),)
    return tuple(os.path.realpath(p) for p in spec.submodule_search_locations or ())


def _shadowed_by_cwd(module: str) -> bool:
    """Whether the working folder holds another ``module`` than the one this process uses.

    That is, whether a process with the working folder first on ``sys.path`` would import
    the top-level package of ``module`` from somewhere else than this process does (e.g.
    an empty folder ``freipose`` there instead of the installed package).
    """
    top = module.partition(".")[0]
    if top == "__main__" or getattr(sys.flags, "safe_path", False):
        return False
    try:
        in_cwd = PathFinder.find_spec(top, [os.getcwd()])
    except (OSError, ImportError, ValueError):
        return False
    if in_cwd is None:
        return False
    loaded = sys.modules.get(top)
    try:
        here = loaded.__spec__ if loaded is not None else importlib.util.find_spec(top)
    except (ImportError, ValueError):
        here = None
    return _spec_location(here) != _spec_location(in_cwd)


def safe_preload(preload: Sequence[str]) -> list[str]:
    """The modules of ``preload`` that the forkserver can import as this process does.

    Modules whose top-level package the working folder shadows are left out (each worker
    imports them itself, with this process's ``sys.path``).
    """
    keep = [m for m in preload if not _shadowed_by_cwd(m)]
    if len(keep) < len(preload):
        dropped = sorted(set(preload) - set(keep))
        log.debug("not preloading %s: the working folder %s shadows them", dropped, os.getcwd())
    return keep


def _exit_cause(pool: ProcessPoolExecutor | None) -> str | None:
    """How the first dead worker of ``pool`` ended (its exit status or signal), if known."""
    # The pool fails its futures before it terminates and joins its workers: wait for its
    # manager thread to finish that, so that no two threads read a worker's status at once.
    manager = getattr(pool, "_executor_manager_thread", None)
    if manager is not None:
        manager.join(5.0)
    procs = getattr(pool, "_processes", None) or {}
    codes = []
    for p in list(procs.values()):
        with contextlib.suppress(AssertionError, OSError, ValueError):
            p.join(1.0)
        if p.exitcode not in (None, 0):
            codes.append(p.exitcode)
    # the pool terminates the other workers (SIGTERM) once one has died
    own = [c for c in codes if c != -signal.SIGTERM] or codes
    if not own:
        return None
    code = own[0]
    if code < 0:
        name = signal.Signals(-code).name if -code in signal.valid_signals() else str(-code)
        oom = " (the system may have run out of memory)" if -code == signal.SIGKILL else ""
        return f"it was killed by {name}{oom}"
    return f"it exited with status {code} (its own error, if any, is printed above)"


def _broken_cause(err: BrokenProcessPool, pool: ProcessPoolExecutor | None) -> str:
    """One line that says why a worker died, from the pool error and the dead workers."""
    remote = err.__cause__
    if remote is not None:
        lines = [ln.strip() for ln in str(remote).splitlines() if ln.strip(" '\"")]
        if lines:
            return lines[-1]
    return _exit_cause(pool) or (
        "it ended without reporting an error (killed, or it failed to start: its own "
        "error, if any, is printed above)"
    )


@contextlib.contextmanager
def worker_errors(
    pool: ProcessPoolExecutor | None = None,
    hint: str = "run again with one job (--jobs 1) to see the error in this process",
) -> Iterator[None]:
    """Turn a pool's ``BrokenProcessPool`` in the block into a one-line :class:`WorkerError`.

    Args:
        pool: the pool whose results the block waits for: its dead workers' exit statuses
            name the cause when the pool error does not.
        hint: what the user can do, appended to the message.

    Yields:
        Nothing; the block runs unchanged.

    Raises:
        WorkerError: ``a worker process died: <cause>; <hint>``.
    """
    try:
        yield
    except BrokenProcessPool as e:
        raise WorkerError(f"a worker process died: {_broken_cause(e, pool)}; {hint}") from e


def pool_context(preload: Sequence[str] = (), start_method: str = "forkserver") -> BaseContext:
    """The multiprocessing context that :func:`process_pool` starts its workers with.

    Args:
        preload: modules the forkserver imports once before it forks the workers (ignored
            with ``"spawn"``; those that the working folder shadows are left to the workers,
            see :func:`safe_preload`).
        start_method: ``"forkserver"`` (used where the platform has it, else ``"spawn"``) or
            ``"spawn"``.

    Returns:
        The context; a ``Manager()`` made from it forks from the same clean server.

    Raises:
        ValueError: unknown ``start_method``.
    """
    if start_method not in START_METHODS:
        raise ValueError(f"start_method must be one of {START_METHODS}, got {start_method!r}")
    if start_method == "forkserver" and "forkserver" in mp.get_all_start_methods():
        ctx = mp.get_context("forkserver")
        ctx.set_forkserver_preload(safe_preload(preload))
        return ctx
    return mp.get_context("spawn")


def _exit_when_gone(pid: int, poll_s: float = 1.0) -> None:
    """Block until process ``pid`` has ended, then end this process at once."""
    try:
        fd = os.pidfd_open(pid)  # Linux: readable when the process ends
    except ProcessLookupError:
        os._exit(1)
    except (AttributeError, OSError):  # no pidfd here: poll
        while True:
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                os._exit(1)
            except PermissionError:
                pass
            time.sleep(poll_s)
    select.select([fd], [], [])
    os._exit(1)


def die_with(pid: int) -> None:
    """End this process as soon as process ``pid`` ends (a daemon thread watches it).

    Args:
        pid: the process to outlive by no more than a moment (the one that started this).
    """
    watcher = threading.Thread(target=_exit_when_gone, args=(pid,), daemon=True)
    watcher.start()


def _init_worker(
    parent: int, initializer: Callable[..., object] | None, initargs: tuple[Any, ...]
) -> None:
    """A pool worker's start: watch ``parent``, then run the caller's initializer."""
    die_with(parent)
    if initializer is not None:
        initializer(*initargs)


def start_manager(ctx: BaseContext) -> SyncManager:
    """A started ``SyncManager`` of ``ctx`` whose server process ends with this process.

    Args:
        ctx: the multiprocessing context (e.g. from :func:`pool_context`).

    Returns:
        The manager (call ``shutdown()`` when done).
    """
    manager = SyncManager(ctx=ctx)
    manager.start(die_with, (os.getpid(),))
    return manager


def process_pool(
    max_workers: int,
    preload: Sequence[str] = (),
    initializer: Callable[..., object] | None = None,
    initargs: tuple[Any, ...] = (),
    start_method: str = "forkserver",
) -> ProcessPoolExecutor:
    """A process pool whose workers start from a clean forkserver (else they are spawned).

    Args:
        max_workers: number of worker processes.
        preload: modules the forkserver imports once (workers fork from it with them loaded).
        initializer: called in every worker when it starts (module level, picklable).
        initargs: arguments of ``initializer``.
        start_method: ``"forkserver"`` (where available, else ``"spawn"``) or ``"spawn"``.

    Returns:
        The executor (use it as a context manager). Its workers end with this process
        (:func:`die_with`), also when it is killed.
    """
    ctx = pool_context(preload, start_method)
    init = partial(_init_worker, os.getpid(), initializer, initargs)
    return ProcessPoolExecutor(max_workers, mp_context=ctx, initializer=init)


def _main_is_a_file() -> bool:
    """Whether ``__main__`` is a script on disk (workers cannot re-import a stdin ``__main__``)."""
    main_file = getattr(sys.modules.get("__main__"), "__file__", None)
    return main_file is not None and Path(main_file).exists()


def run_jobs(
    fn: Callable[[J], R],
    jobs: Sequence[J],
    n_workers: int,
    desc: str,
    progress: bool | None,
    start_method: str = "spawn",
) -> list[R]:
    """``[fn(job) for job in jobs]`` in ``n_workers`` processes, with a progress bar.

    With one worker, or when ``__main__`` is interactive or read from stdin (new workers
    could not import it), the jobs run in this process under one OpenCV thread (the
    caller's setting is restored afterwards), like the workers, which set one OpenCV thread
    for themselves.

    Args:
        fn: module-level (picklable) function of one job.
        jobs: the jobs (picklable).
        n_workers: worker processes.
        desc: progress bar label.
        progress: show the bar (None: only on a terminal).
        start_method: how the workers start (see :func:`process_pool`). The default is
            ``"spawn"``: a process has one forkserver, whose preloaded modules are fixed by
            the first pool that starts it, so jobs that need no preloading leave it to the
            pools that do (the demo renders and then detects boards in one process).

    Returns:
        The results, in the order of ``jobs``.
    """
    disable = None if progress is None else not progress
    if not jobs:
        return []
    if n_workers > 1 and not _main_is_a_file():
        n_workers = 1
    if n_workers <= 1:
        from freipose.io.video import opencv_threads

        with opencv_threads(1):
            return [fn(j) for j in progress_bar(jobs, desc=desc, disable=disable)]
    hint = "run again with one worker (--workers 1) to see the error in this process"
    with process_pool(n_workers, start_method=start_method) as ex, worker_errors(ex, hint):
        return list(progress_bar(ex.map(fn, jobs), total=len(jobs), desc=desc, disable=disable))


__all__ = [
    "WorkerError",
    "choose_threads",
    "cpu_cores",
    "die_with",
    "other_load",
    "pool_context",
    "process_pool",
    "run_jobs",
    "safe_preload",
    "start_manager",
    "worker_errors",
]
