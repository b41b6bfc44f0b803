"""The demo's step names and its ``OUTDIR/.demo/<step>.done`` marker files.

A finished step leaves a marker (JSON: the step, the preset, the FreiPose version, the
step's run time and its results). Later steps read the results of earlier ones from these
markers, and the runner skips every step that has one.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from freipose import __version__
from freipose.demo.presets import DemoPreset
from freipose.errors import FreiPoseError
from freipose.io.atomic import atomic_write_text

STEPS = ("synth", "calibrate", "labels", "train", "predict", "evaluate", "analyze", "report")
MARKER_DIR = ".demo"


class DemoError(FreiPoseError):
    """A demo run that cannot start: unknown preset, unusable or mismatched output folder."""


def marker_path(out: Path, step: str) -> Path:
    """The marker file ``out/.demo/<step>.done`` of ``step``."""
    return out / MARKER_DIR / f"{step}.done"


def read_marker(out: Path, step: str) -> dict[str, Any] | None:
    """The marker of ``step`` in the demo folder ``out``; None when missing or unreadable."""
    p = marker_path(out, step)
    if not p.is_file():
        return None
    try:
        return json.loads(p.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return None


def step_results(out: Path, step: str) -> dict[str, Any]:
    """The ``results`` of the finished ``step`` (its marker must exist).

    Raises:
        DemoError: ``step`` has not finished (no readable marker).
    """
    marker = read_marker(out, step)
    if marker is None:
        raise DemoError(f"{marker_path(out, step)}: the demo step {step!r} has not finished")
    return marker["results"]


def write_marker(
    out: Path, preset: DemoPreset, step: str, results: dict[str, Any], seconds: float
) -> None:
    """Write the marker of the finished ``step`` (atomically).

    Args:
        out: the demo folder.
        preset: the run's preset (stored so that another preset is refused later).
        step: the step's name.
        results: the step's results (JSON-serializable; numpy scalars, arrays and paths too).
        seconds: the step's run time.
    """
    p = marker_path(out, step)
    p.parent.mkdir(parents=True, exist_ok=True)
    doc = {
        "step": step,
        "preset": preset.to_dict(),
        "freipose_version": __version__,
        "seconds": round(seconds, 2),
        "results": results,
    }
    atomic_write_text(p, json.dumps(doc, indent=2, default=_json_default) + "\n")


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serializable: {type(o)}")


def check_outdir(out: Path, preset: DemoPreset) -> None:
    """Refuse to mix presets in one folder (the finished steps would not match).

    Raises:
        DemoError: a step in ``out`` was finished with another preset.
    """
    for step in STEPS:
        m = read_marker(out, step)
        if m is not None and m.get("preset") != preset.to_dict():
            other = m.get("preset", {}).get("name", "?")
            raise DemoError(
                f"{out} holds a demo run with other settings (preset {other!r}, step {step} "
                f"done); use another output folder or delete {out} to start over"
            )
