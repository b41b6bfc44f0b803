"""freipose.workers: the process pool and the job runner."""

from __future__ import annotations

import math
import sys

import cv2
import pytest

from freipose.workers import pool_context, process_pool, run_jobs


def test_run_jobs_in_process_keeps_order_and_opencv_threads():
    before = cv2.getNumThreads()
    assert run_jobs(math.sqrt, [9.0, 4.0, 1.0], 1, "test", False) == [3.0, 2.0, 1.0]
    assert cv2.getNumThreads() == before
    assert run_jobs(math.sqrt, [], 4, "test", False) == []


def test_run_jobs_in_worker_processes():
    assert run_jobs(math.sqrt, [16.0, 25.0, 36.0], 2, "test", False) == [4.0, 5.0, 6.0]


def test_process_pool_runs_the_initializer():
    # spawn: the forkserver (one per process) is left to the pools that preload modules
    with process_pool(1, initializer=math.sqrt, initargs=(2.0,), start_method="spawn") as ex:
        assert ex.submit(math.factorial, 5).result() == 120


def test_pool_context_start_methods():
    assert pool_context(start_method="spawn").get_start_method() == "spawn"
    with pytest.raises(ValueError, match="start_method"):
        pool_context(start_method="fork")


_REALLOCATE = """
import resource, sys
import torch
from freipose.workers import keep_freed_memory
if sys.argv[1] == "keep" and not keep_freed_memory():
    print("unsupported"); raise SystemExit
x = torch.ones(16 << 20)  # 64 MB: above glibc's largest mmap threshold
faults = []
for _ in range(8):  # like a network step: temporaries of 64 MB each, freed again
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    y = torch.nn.functional.relu(x * 2.0) + 1.0
    del y
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(sum(faults[1:]))
"""


def test_keep_freed_memory_reuses_large_blocks():
    import subprocess

    def faults(mode: str) -> str:
        run = subprocess.run([sys.executable, "-c", _REALLOCATE, mode], capture_output=True)
        assert run.returncode == 0, run.stderr.decode()
        return run.stdout.decode().strip()

    kept = faults("keep")
    if kept == "unsupported":
        pytest.skip("the C library is not glibc: keep_freed_memory changes nothing here")
    # by default every temporary is a fresh mmap: 3 x 16384 pages of 4 kB per step, faulted
    # in again each time; kept, most steps reuse freed blocks (how many depends on where
    # small allocations land between them: 0-24 % of the default's faults in 45 runs)
    default = int(faults("default"))
    assert default > 7 * 2 * 16384
    assert int(kept) < default / 2
