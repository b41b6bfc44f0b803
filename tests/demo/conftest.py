"""The tiny demo run that the demo tests share (one run per test session).

The demo runs as a user would start it under nohup or in a cluster job: in a subprocess
whose standard output and error go to a pipe. The arrival time of every line is kept, so
that the progress test reads the same run as the tests of the demo's outputs.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

#: seconds between progress lines of the shared run (``FREIPOSE_PROGRESS_SECONDS``)
PROGRESS_SECONDS = 2


def run_piped_demo(out: Path) -> tuple[int, list[tuple[float, str]]]:
    """``freipose demo OUT --preset tiny`` piped -> (exit code, [(seconds, line), ...])."""
    env = {**os.environ, "FREIPOSE_PROGRESS_SECONDS": str(PROGRESS_SECONDS),
           "PYTHONUNBUFFERED": "1"}  # fmt: skip
    cmd = [sys.executable, "-m", "freipose.cli.main", "demo", str(out), "--preset", "tiny"]
    t0 = time.monotonic()
    lines = []
    with subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env
    ) as proc:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append((time.monotonic() - t0, line.rstrip("\n")))
        rc = proc.wait()
    return rc, lines


@pytest.fixture(scope="session")
def tiny_demo_lines(tmp_path_factory):
    """The shared tiny demo: its folder and its lines with their arrival times."""
    out = tmp_path_factory.mktemp("demo") / "demo_out"
    rc, lines = run_piped_demo(out)
    assert rc == 0, "\n".join(ln for _, ln in lines)
    return out, lines


@pytest.fixture(scope="session")
def tiny_demo(tiny_demo_lines):
    """``freipose demo OUT --preset tiny``: the folder and the printed output."""
    out, lines = tiny_demo_lines
    return out, "\n".join(ln for _, ln in lines) + "\n"
