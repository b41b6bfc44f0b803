"""The pose trainer's loss history: ``log.csv`` and its plot ``log.png``.

Columns (:data:`LOG_COLUMNS`): ``step`` (optimizer steps done), ``lr``, the total ``loss``
and its terms (averaged over the steps since the previous row; ``u_*`` the terms of the
``[unlabeled]`` losses), the validation median JPE
of P0 and P1 in mm when computed, and ``seconds`` since the training started or resumed.
"""

from __future__ import annotations

import csv
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

from freipose.io.atomic import atomic_write_text
from freipose.io.figures import new_figure, save_figure

# the terms of the [unlabeled] losses (freipose.nn.unlabeled_losses), empty without them
UNLABELED_TERMS = ("u_multiview", "u_p0p1", "u_temporal", "u_equivariance", "u_bones", "u_teacher")

LOG_COLUMNS = [
    "step",
    "lr",
    "loss",
    "p0",
    "aux",
    "vol",
    "2d",
    "conf",
    "p1",
    *UNLABELED_TERMS,
    "val_jpe_p0",
    "val_jpe_p1",
    "seconds",
]


def read_log(path: Path, upto: int) -> list[dict[str, str]]:
    """The rows of a ``log.csv`` (column name to text) up to step ``upto``.

    Args:
        path: the log file; a missing file has no rows.
        upto: keep only rows with ``step <= upto``.

    Returns:
        The rows in file order.
    """
    if not path.exists():
        return []
    with path.open(newline="") as f:
        return [r for r in csv.DictReader(f) if r.get("step") and int(r["step"]) <= upto]


def log_line(row: dict[str, Any]) -> str:
    """One log row as a CSV line of :data:`LOG_COLUMNS` (empty where the row has no value)."""
    return ",".join(str(row.get(c, "")) for c in LOG_COLUMNS)


def append_log(path: Path, row: dict[str, Any]) -> None:
    """Append one row to the log file ``path``."""
    with path.open("a") as f:
        f.write(log_line(row) + "\n")


def write_log(path: Path, rows: list[dict[str, Any]]) -> None:
    """Write the header and ``rows`` to the log file ``path`` (atomically)."""
    lines = [",".join(LOG_COLUMNS)]
    lines.extend(log_line(r) for r in rows)
    atomic_write_text(path, "\n".join(lines) + "\n")


def _log_values(rows: list[dict[str, str]], column: str) -> np.ndarray:
    """The values of ``column`` in ``rows`` (NaN where empty)."""
    return np.array([float(r[column]) if r.get(column) not in (None, "") else np.nan for r in rows])


# the validation curves of each model kind: log column, legend (the baseline has one estimate,
# which its log repeats under both columns)
VALIDATION_CURVES: Mapping[str, tuple[tuple[str, str], ...]] = MappingProxyType({
    "voxel": (("val_jpe_p0", "P0 (3D network)"), ("val_jpe_p1", "P1 (refined)")),
    "baseline": (("val_jpe_p1", "triangulated 2D keypoints"),),
})  # fmt: skip


def plot_log(csv_path: str | Path, png_path: str | Path, kind: str = "voxel") -> None:
    """Plot the training log: losses (log scale) and validation JPE against the step.

    Args:
        csv_path: the run's ``log.csv``.
        png_path: the PNG to write (nothing is written for an empty log).
        kind: the model's ``[model] kind``: ``voxel`` (curves of P0 and P1) or
            ``baseline`` (one estimate, one curve).
    """
    rows = read_log(Path(csv_path), 1 << 62)
    if not rows:
        return
    fig = new_figure((10, 4))
    a1, a2 = fig.subplots(1, 2)
    steps = np.array([int(r["step"]) for r in rows])
    for c in ("loss", "p0", "aux", "vol", "2d", "conf", "p1"):
        v = _log_values(rows, c)
        if np.isfinite(v).any():
            a1.plot(steps, v, label=c)
    a1.set_yscale("log")
    a1.set_xlabel("step")
    a1.set_ylabel("loss (log scale)")
    a1.set_title("training losses")
    a1.legend(fontsize=8)
    for c, name in VALIDATION_CURVES[kind]:
        v = _log_values(rows, c)
        ok = np.isfinite(v)
        if ok.any():
            a2.plot(steps[ok], v[ok], "o-", label=name)
    a2.set_xlabel("step")
    a2.set_ylabel("median JPE (mm)")
    a2.set_title("validation")
    if a2.get_legend_handles_labels()[0]:
        a2.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, png_path, dpi=100, format="png")
