"""Running ``freipose`` commands inside a benchmark's process, as on the command line."""

from __future__ import annotations

import time
from pathlib import Path


def freipose(args: list[str]) -> float:
    """Run ``freipose ARGS`` in this process (quiet); returns its wall time in seconds.

    Raises:
        SystemExit: the command failed (a benchmark stops at the first failing command).
    """
    from freipose.cli.main import cli

    t0 = time.perf_counter()
    try:
        cli.main(["-q", *args], standalone_mode=False)
    except Exception as exc:
        raise SystemExit(f"freipose {' '.join(args)} failed: {exc}") from exc
    return time.perf_counter() - t0


def step(done: Path, args: list[str]) -> float | None:
    """Run a command unless its output ``done`` exists; its wall time, None when skipped."""
    return None if done.exists() else freipose(args)
