"""Worker processes: one way to start a process pool and one runner for lists of jobs.

:func:`process_pool` starts workers from a clean forkserver process where the platform has
one (forking a process whose OpenCV or FFmpeg thread pools are running can deadlock the
child), with the given modules imported once in the server so that every worker forks
ready to run; elsewhere the workers are spawned. :func:`run_jobs` maps a function over a
list of jobs in such a pool, or in this process when one worker is asked for.
"""

from __future__ import annotations

import multiprocessing as mp
import sys
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from multiprocessing.context import BaseContext
from pathlib import Path
from typing import Any, TypeVar

from tqdm import tqdm

J = TypeVar("J")
R = TypeVar("R")

START_METHODS = ("forkserver", "spawn")


def pool_context(preload: Sequence[str] = (), start_method: str = "forkserver") -> BaseContext:
    """The multiprocessing context that :func:`process_pool` starts its workers with.

    Args:
        preload: modules the forkserver imports once before it forks the workers (ignored
            with ``"spawn"``).
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
        ctx.set_forkserver_preload(list(preload))
        return ctx
    return mp.get_context("spawn")


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
        The executor (use it as a context manager).
    """
    ctx = pool_context(preload, start_method)
    return ProcessPoolExecutor(
        max_workers, mp_context=ctx, initializer=initializer, initargs=initargs
    )


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
            return [fn(j) for j in tqdm(jobs, desc=desc, disable=disable)]
    with process_pool(n_workers, start_method=start_method) as ex:
        return list(tqdm(ex.map(fn, jobs), total=len(jobs), desc=desc, disable=disable))


__all__ = ["pool_context", "process_pool", "run_jobs"]
