"""``OUTDIR/summary.json``: every figure the demo prints, read from its step markers.

Written by the runner after every run (a partial run gives the finished steps' figures):
``preset``, ``init`` (the starting weights), ``budgets`` (training steps per network),
``seconds`` (per step and in total), ``calibration`` (largest errors against the true rig),
``labels`` (the training labels' error against the truth), ``detector`` (recall at IoU 0.5,
median 3D centre error and the other detection metrics on held-out instants),
``evaluation`` (the held-out JPE per method, the whole pipeline's JPE, and what else the
evaluation step reports) and ``analysis`` (the attribution on the predicted and on the true
poses). The schema is in ``docs/formats.md``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from freipose import __version__
from freipose.demo.markers import STEPS, read_marker
from freipose.demo.presets import DemoPreset
from freipose.io.atomic import atomic_write_text

SUMMARY = "summary.json"


def _training(results: dict[str, Any]) -> dict[str, Any]:
    """The training step's figures: budgets, starting weights, detector metrics, last logs."""
    out: dict[str, Any] = {k: results[k] for k in ("init", "budgets") if k in results}
    for net in ("pose", "baseline"):
        if "last_log" in results.get(net, {}):
            out[f"{net}_last_log"] = results[net]["last_log"]
    return out


def _finite(obj: Any) -> Any:
    """``obj`` with every NaN or infinite number replaced by None (strict JSON)."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_finite(v) for v in obj]
    return obj


def build_summary(out: Path, preset: DemoPreset) -> dict[str, Any]:
    """The summary of the demo run in ``out`` from the markers of its finished steps.

    Args:
        out: the demo folder.
        preset: the run's preset.

    Returns:
        The summary (see the module docstring); steps without a marker are left out, and
        undefined figures (NaN) are None.
    """
    res: dict[str, Any] = {"preset": preset.name, "freipose_version": __version__}
    seconds: dict[str, float] = {}
    for step in STEPS:
        m = read_marker(out, step)
        if m is None:
            continue
        seconds[step] = float(m.get("seconds", 0.0))
        r = m.get("results", {})
        if step == "calibrate":
            res["calibration"] = r.get("summary", {})
        elif step == "labels":
            res["labels"] = r
        elif step == "train":
            res.update(_training(r))
            res["detector"] = r.get("detector", {}).get("metrics", {})
        elif step == "evaluate":
            res["evaluation"] = r
        elif step == "analyze":
            res["analysis"] = r
    res["seconds"] = {**seconds, "total": round(sum(seconds.values()), 2)}
    return _finite(res)


def write_summary(out: Path, preset: DemoPreset) -> Path:
    """Write ``out/summary.json`` (atomically) and return its path.

    Args:
        out: the demo folder.
        preset: the run's preset.

    Returns:
        The path of ``summary.json``.
    """
    path = out / SUMMARY
    text = json.dumps(build_summary(out, preset), indent=2, allow_nan=False)
    atomic_write_text(path, text + "\n")
    return path
