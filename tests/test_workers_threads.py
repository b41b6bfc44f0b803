"""choose_threads: the thread count from the free cores, --threads and OMP_NUM_THREADS."""

from __future__ import annotations

import logging

import pytest

import freipose.workers as workers
from freipose.errors import FreiPoseError


@pytest.fixture
def machine(monkeypatch):
    """Set the machine's cores and other processes' load: machine(cores, load)."""
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)

    def set_(cores: int, load: float) -> None:
        monkeypatch.setattr(workers, "cpu_cores", lambda: cores)
        monkeypatch.setattr(workers, "other_load", lambda: load)

    return set_


@pytest.mark.parametrize(
    ("cores", "load", "n_workers", "want"),
    [(2, 0.1, 1, 2), (2, 1.3, 1, 1), (2, 5.0, 1, 1), (8, 0.0, 2, 4), (8, 2.6, 2, 2), (1, 0, 1, 1)],
)
def test_threads_follow_the_free_cores(machine, cores, load, n_workers, want):
    machine(cores, load)
    assert workers.choose_threads(None, n_workers) == want


def test_explicit_count_and_environment_win_and_the_choice_is_logged(machine, monkeypatch, caplog):
    machine(2, 1.3)
    with caplog.at_level(logging.INFO, logger="freipose.workers"):
        assert workers.choose_threads(None) == 1
    assert "using 1 PyTorch thread (2 cores, load 1.3)" in caplog.text
    assert workers.choose_threads(3) == 3
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    assert workers.choose_threads(None) == 2
    assert workers.choose_threads(1) == 1
    monkeypatch.setenv("OMP_NUM_THREADS", "two")
    with pytest.raises(FreiPoseError, match="OMP_NUM_THREADS"):
        workers.choose_threads(None)
    with pytest.raises(FreiPoseError, match="--threads"):
        workers.choose_threads(0)


def test_other_load_from_busy_time_or_the_load_average(monkeypatch):
    cpus = workers.os.sched_getaffinity(0)
    samples = iter([(100.0, 1000.0), (175.0, 1100.0)])  # 75 % busy over the window
    monkeypatch.setattr(workers, "_cpu_times", lambda c: next(samples))
    assert workers.other_load(0.01) == pytest.approx(0.75 * len(cpus), abs=0.05)
    monkeypatch.setattr(workers, "_cpu_times", lambda c: None)
    monkeypatch.setattr(workers.os, "getloadavg", lambda: (2.3, 1.0, 0.5))
    assert workers.other_load(0.01) == pytest.approx(1.3)


def test_cpu_times_reads_proc_stat():
    got = workers._cpu_times(workers.os.sched_getaffinity(0))
    if got is None:
        pytest.skip("no /proc/stat on this system")
    busy, total = got
    assert 0 <= busy <= total and total > 0
