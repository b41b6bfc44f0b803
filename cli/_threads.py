"""The ``--threads`` option of the commands that compute (``train``, ``predict``, ``demo``)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import click

THREADS_HELP = (
    "PyTorch and OpenCV threads [default: the cores that other processes leave free, "
    "or OMP_NUM_THREADS where set]. On a shared machine, more threads than free cores "
    "run several times slower."
)


def threads_option() -> Callable[[Any], Any]:
    """``--threads N`` (default None: chosen by :func:`freipose.workers.choose_threads`)."""
    return click.option("--threads", type=int, default=None, help=THREADS_HELP)


def use_threads(threads: int | None, workers: int = 1) -> int:
    """Choose the thread count and set it for PyTorch and OpenCV in this process.

    The process also keeps the memory of freed tensors for reuse
    (:func:`freipose.workers.keep_freed_memory`): repeated network steps run without page
    faults.

    Args:
        threads: the ``--threads`` value (None: chosen from the free cores).
        workers: processes that each run that many threads.

    Returns:
        The thread count set.
    """
    import cv2
    import torch

    from freipose.workers import choose_threads, keep_freed_memory

    n = choose_threads(threads, workers)
    torch.set_num_threads(n)
    cv2.setNumThreads(n)
    keep_freed_memory()
    return n
