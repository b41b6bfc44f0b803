"""Worker processes end with the process that started them, also when it is killed."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="reads process states from /proc"
)

_PARENT = """
import os, sys, time
from multiprocessing import resource_tracker
from freipose.workers import pool_context, process_pool, start_manager

def job(path):
    with open(path, "a") as f:
        f.write(f"{os.getpid()} {os.getppid()}\\n")  # the worker and the forkserver
    time.sleep(120)

if __name__ == "__main__":
    out = sys.argv[1]
    manager = start_manager(pool_context(["os"]))
    with process_pool(2, preload=["os"]) as ex:
        for _ in range(2):
            ex.submit(job, out)
        tracker = resource_tracker._resource_tracker._pid
        with open(out, "a") as f:
            f.write(f"{manager._process.pid} {tracker}\\n")
        time.sleep(120)
"""


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, ended but not yet reaped, does not)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rpartition(")")[2].split()[0] != "Z"


def test_pool_manager_forkserver_and_tracker_end_when_the_parent_is_killed(tmp_path):
    script, out = tmp_path / "parent.py", tmp_path / "pids.txt"
    script.write_text(_PARENT)
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    parent = subprocess.Popen([sys.executable, str(script), str(out)], env=env, cwd=tmp_path)
    pids: set[int] = set()
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:  # two workers and the parent's line
            lines = out.read_text().splitlines() if out.exists() else []
            if len(lines) >= 3:
                pids = {int(p) for ln in lines for p in ln.split()} - {parent.pid}
                break
            time.sleep(0.2)
        assert len(pids) >= 4, f"the processes did not start: {lines}"  # workers, server...
        parent.send_signal(signal.SIGKILL)
        parent.wait()
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and any(_alive(p) for p in pids):
            time.sleep(0.2)
        left = sorted(p for p in pids if _alive(p))
        assert not left, f"processes left running after kill -9 of their parent: {left}"
    finally:
        parent.kill()
        for p in pids:  # only the processes this test started
            if _alive(p):
                os.kill(p, signal.SIGKILL)
