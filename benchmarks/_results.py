"""One home for benchmark results: every script writes its figures here as JSON.

``write_result(name, figures)`` writes
``benchmarks/results/<name>/<UTC date>_<commit>_<cpu kind>-<host hash>_<n>.json`` (atomically)
with the machine (platform, CPU model, cores, memory), the CPU flags that change float results,
the CPU kind (``avx512``, ``avx2`` or ``other``), the Python, PyTorch and NumPy versions, the
UTC time, the git commit (and whether the tree had uncommitted changes), the command line and
the figures. ``load_results()`` reads them back; ``benchmarks/report.py`` turns them into
``docs/benchmarks.md``. The environment variable ``FREIPOSE_RESULTS_DIR`` (used by the tests)
sends the files elsewhere, and ``FREIPOSE_RESULTS_DIR=off`` writes none.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import math
import os
import platform
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

from freipose.io.atomic import atomic_write_text

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
ENV = "FREIPOSE_RESULTS_DIR"
SCHEMA = 1
# flags that select the kernels (and so the rounding) of float code in NumPy and PyTorch
FLAGS = (
    "sse4_2",
    "avx",
    "avx2",
    "fma",
    "f16c",
    "avx512f",
    "avx512bw",
    "avx512vl",
    "avx512_vnni",
    "avx512_bf16",
    "avx512_fp16",
    "avx_vnni",
    "amx_tile",
    "amx_bf16",
    "amx_int8",
)


def results_dir() -> Path | None:
    """The results folder: ``$FREIPOSE_RESULTS_DIR`` if set (None for ``off``), else the repo's."""
    env = os.environ.get(ENV, "")
    if env.lower() == "off":
        return None
    return Path(env) if env else RESULTS


def _cpuinfo() -> tuple[str, set[str]]:
    """The CPU's model name and flags from /proc/cpuinfo (empty where there is none)."""
    try:
        text = Path("/proc/cpuinfo").read_text(encoding="utf-8", errors="replace")
    except OSError:
        return platform.processor(), set()
    model = re.search(r"^model name\s*:\s*(.+)$", text, re.M)
    flags = re.search(r"^(?:flags|Features)\s*:\s*(.+)$", text, re.M)
    name = model.group(1).strip() if model else platform.processor()
    return name, set(flags.group(1).split()) if flags else set()


def cpu_kind(flags: set[str]) -> str:
    """``avx512`` (AVX-512F), ``avx2`` or ``other``: the kinds whose float results differ."""
    if "avx512f" in flags:
        return "avx512"
    return "avx2" if "avx2" in flags else "other"


def _memory_gib() -> float | None:
    """Total memory in GiB from /proc/meminfo (None where unknown)."""
    try:
        text = Path("/proc/meminfo").read_text(encoding="utf-8")
    except OSError:
        return None
    m = re.search(r"^MemTotal:\s*(\d+) kB", text, re.M)
    return round(int(m.group(1)) / 2**20, 1) if m else None


def _versions() -> dict[str, str | None]:
    """Python, NumPy and PyTorch versions and the CPU capability PyTorch's kernels use."""
    out: dict[str, str | None] = {"python": platform.python_version()}
    try:
        import numpy

        out["numpy"] = numpy.__version__
    except ImportError:
        out["numpy"] = None
    try:
        import torch

        out["torch"] = torch.__version__
        out["torch_cpu_capability"] = torch.backends.cpu.get_cpu_capability()
    except (ImportError, AttributeError):
        out.setdefault("torch", None)
    return out


def machine() -> dict[str, Any]:
    """The machine a result was measured on (no host name, only a short hash of it)."""
    model, flags = _cpuinfo()
    host = hashlib.sha256(platform.node().encode()).hexdigest()[:6]
    return {
        "platform": platform.platform(),
        "cpu_model": model,
        "cores": os.cpu_count(),
        "memory_gib": _memory_gib(),
        "cpu_flags": sorted(f for f in FLAGS if f in flags),
        "cpu_kind": cpu_kind(flags),
        "host_hash": host,
    }


def git_state(root: Path = ROOT) -> dict[str, Any]:
    """The commit of ``root`` (short and full) and whether tracked files differ from it."""

    def git(*args: str) -> str:
        res = subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, check=False)
        return res.stdout.strip() if res.returncode == 0 else ""

    full = git("rev-parse", "HEAD")
    dirty = bool(git("status", "--porcelain", "--untracked-files=no")) if full else None
    return {"commit": full or None, "short": full[:8] or "nogit", "dirty": dirty}


def _finite(obj: Any) -> Any:
    """``obj`` as strict JSON: NaN and infinities become None, NumPy scalars plain numbers."""
    if hasattr(obj, "item") and not isinstance(obj, (list, dict, str)):
        obj = obj.item()
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return obj


def write_result(
    name: str,
    figures: dict[str, Any],
    *,
    command: list[str] | None = None,
    extra: dict[str, Any] | None = None,
) -> Path | None:
    """Record one run of benchmark ``name``: its figures with the machine, versions and commit.

    Args:
        name: the benchmark (the results subfolder), e.g. ``"synth"``.
        figures: the figures the run printed: numbers (NaN is written as null), strings, or
            nested dicts of them.
        command: the command line (default ``sys.argv``, the script's path relative to the repo).
        extra: settings worth keeping with the figures (``seed``, sizes, ...).

    Returns:
        The path written, or None when ``FREIPOSE_RESULTS_DIR=off``.
    """
    folder = results_dir()
    if folder is None:
        return None
    now = dt.datetime.now(dt.timezone.utc)
    mach, git = machine(), git_state()
    argv = list(sys.argv if command is None else command)
    if argv and (Path(argv[0]).is_absolute() or Path(argv[0]).is_file()):
        path0 = Path(argv[0]).absolute()  # a script run from another folder: from the repo
        argv[0] = str(path0.relative_to(ROOT)) if path0.is_relative_to(ROOT) else str(path0)
    record = {
        "schema": SCHEMA,
        "benchmark": name,
        "date": now.strftime("%Y-%m-%dT%H:%M:%SZ"),
        "git": {"commit": git["commit"], "dirty": git["dirty"]},
        "machine": mach,
        "versions": _versions(),
        "command": argv,
        "extra": extra or {},
        "figures": figures,
    }
    text = json.dumps(_finite(record), indent=2, allow_nan=False) + "\n"
    out = folder / name
    out.mkdir(parents=True, exist_ok=True)
    stem = f"{now:%Y-%m-%d}_{git['short']}_{mach['cpu_kind']}-{mach['host_hash']}"
    n = 1
    while (out / f"{stem}_{n}.json").exists():
        n += 1
    path = out / f"{stem}_{n}.json"
    atomic_write_text(path, text)
    print(f"result recorded: {path}", file=sys.stderr)
    return path


def load_results(name: str | None = None, folder: Path | None = None) -> list[dict[str, Any]]:
    """Every recorded result (of benchmark ``name``, or all), oldest first.

    Args:
        name: a benchmark name, or None for all of them.
        folder: the results folder (default: as ``write_result`` writes).

    Returns:
        The records, each with ``path`` (the file) added; sorted by date and file name.
    """
    root = folder if folder is not None else results_dir()
    if root is None or not root.is_dir():
        return []
    pattern = f"{name}/*.json" if name else "*/*.json"
    out = []
    for p in sorted(root.glob(pattern)):
        if p.name.startswith("."):
            continue
        rec = json.loads(p.read_text(encoding="utf-8"))
        rec["path"] = p
        out.append(rec)
    return sorted(out, key=lambda r: (r.get("date", ""), r["path"].name))
