"""freipose.workers: the process pool and the job runner."""

from __future__ import annotations

import math

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
