"""The detector trainer's loss history, ``log.csv`` next to its checkpoints.

Columns (:data:`LOG_COLUMNS`): ``step`` (optimizer steps done), ``lr`` (learning rate after
the step), ``loss``, ``heat``, ``size``, ``offset`` (the total loss and its heat-map, size
and offset terms, averaged over the steps since the previous row) and ``seconds`` (since the
training started or resumed). A row is written every ``log_every`` steps and at the end.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np

from freipose.io.atomic import atomic_write_text

LOG = "log.csv"
LOG_COLUMNS = ("step", "lr", "loss", "heat", "size", "offset", "seconds")


def read_log(path: Path, upto: int | None = None) -> list[dict[str, str]]:
    """The rows of a detector ``log.csv`` (column name to text), up to step ``upto``.

    Args:
        path: the ``log.csv`` file; a missing file has no rows.
        upto: keep only rows with ``step <= upto`` (None: every row).

    Returns:
        The rows in file order; the columns are :data:`LOG_COLUMNS`.
    """
    if not path.is_file():
        return []
    with path.open(newline="") as f:
        rows = [r for r in csv.DictReader(f) if r.get("step")]
    return [r for r in rows if upto is None or int(r["step"]) <= upto]


def write_log(path: Path, rows: list[dict[str, Any]]) -> None:
    """Write ``rows`` (column name to value) as the detector ``log.csv`` (atomically)."""
    lines = [",".join(LOG_COLUMNS)]
    lines += [",".join(str(r.get(c, "")) for c in LOG_COLUMNS) for r in rows]
    atomic_write_text(path, "\n".join(lines) + "\n")


def log_row(
    step: int, lr: float, window: list[float], parts: list[dict[str, float]], seconds: float
) -> dict[str, Any]:
    """One ``log.csv`` row: losses averaged over the steps since the previous row.

    Args:
        step: optimizer steps done.
        lr: the learning rate after the step.
        window: the total losses of the steps since the previous row.
        parts: the ``heat``, ``size`` and ``offset`` terms of the same steps.
        seconds: time since the training started or resumed.

    Returns:
        The row (column name to formatted text).
    """
    row: dict[str, Any] = {"step": step, "lr": f"{lr:.3g}", "loss": f"{np.mean(window):.6g}"}
    for k in ("heat", "size", "offset"):
        row[k] = f"{np.mean([p[k] for p in parts]):.6g}"
    row["seconds"] = f"{seconds:.1f}"
    return row
