"""Record runs of ``freipose demo`` as results: the key figures of each run's ``summary.json``.

Runs the demo for the given training seeds (``--seed 0 1 2``, each into
``--work/demo_seed<S>``, resumed when a folder holds a partial run) or reads demo folders that
finished before (``--from DIR...``), and records each as a result ``demo`` (see
``benchmarks/_results.py``): the calibration's largest errors, the detector's recall and
centre error, the held-out median JPE of voxel P1, voxel P0 and the baseline, the whole
pipeline's JPE per day, the best single variable and its F1, the stimulated paw's share among
the 5 and 10 best variables, the balanced accuracy on the raw and on the smoothed predicted
poses, the number of significant variables, and the wall time per step and in total; with
the preset, the starting weights and the networks' training schedule (steps, learning rate
and the step where it drops).

    python benchmarks/demo.py --seed 0 1 2 --work runs          # 5-7 min per seed, 2 cores
    python benchmarks/demo.py --from runs/demo_seed0 runs/demo_seed1
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

from _results import write_result

from freipose.demo.markers import STEPS, read_marker
from freipose.demo.summary import SUMMARY

POSES = ("predicted", "smoothed", "truth")
METHODS = ("voxel_P1", "voxel_P0", "baseline")
# the schedule recorded with each run (the networks' budgets: runs of other ones differ)
SCHEDULE_KEYS = ("steps", "lr", "lr_decay_steps")


def _get(d: dict[str, Any], *keys: str) -> Any:
    """``d[k1][k2]...`` or None where a key is missing."""
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


def _analysis(a: dict[str, Any], poses: str) -> dict[str, Any]:
    """The attribution's key figures on one kind of poses."""
    r = a.get(poses) or {}
    top = r.get("top_variables") or []
    part = a.get("stimulated_part")
    out: dict[str, Any] = {
        "balanced_accuracy": r.get("balanced_accuracy"),
        "best_variable": top[0]["variable"] if top else None,
        "best_f1": top[0]["f1"] if top else None,
        "paw_share_top5": sum(t["part"] == part for t in top[:5]) / 5 if len(top) >= 5 else None,
        "paw_share_top10": r.get("top10_share_stimulated_part"),
        "paw_best_rank": r.get("stimulated_best_rank"),
        "significant": r.get("significant"),
    }
    return {k: v for k, v in out.items() if v is not None}


def demo_figures(summary: dict[str, Any], seconds: dict[str, float]) -> dict[str, Any]:
    """The key figures of one demo run.

    Args:
        summary: the run's ``summary.json``.
        seconds: wall time per step (from the step markers) and ``total``.

    Returns:
        Nested figures: ``calibration``, ``detector``, ``held_out_jpe_mm`` (per method),
        ``pipeline_jpe_mm`` (per day), ``analysis`` (per kind of poses) and ``seconds``.
    """
    cal = summary.get("calibration") or {}
    det = summary.get("detector") or {}
    labels = _get(summary, "evaluation", "labels") or {}
    pipe = _get(summary, "evaluation", "pipeline") or {}
    analysis = summary.get("analysis") or {}
    figures: dict[str, Any] = {
        "calibration": {
            k: cal[k]
            for k in ("max_center_mm", "max_rotation_deg", "max_focal_percent", "max_rms_px")
            if k in cal
        },
        "detector": {k: det[k] for k in ("recall", "median_center_error") if k in det},
        "held_out_jpe_mm": {m: labels[m]["median"] for m in METHODS if m in labels},
        "pipeline_jpe_mm": {day: r["median"] for day, r in pipe.items() if "median" in r},
        "analysis": {p: _analysis(analysis, p) for p in POSES if analysis.get(p)},
        "seconds": seconds,
    }
    return {k: v for k, v in figures.items() if v}


def step_seconds(folder: Path, summary: dict[str, Any]) -> dict[str, float]:
    """Wall time per step from the markers in ``folder/.demo`` (else the summary's), and total."""
    out = {}
    for step in STEPS:
        m = read_marker(folder, step)
        if m is not None and "seconds" in m:
            out[step] = round(float(m["seconds"]), 2)
    if not out:
        out = {k: v for k, v in (summary.get("seconds") or {}).items() if k != "total"}
    return {**out, "total": round(sum(out.values()), 2)}


def marker_pose(folder: Path) -> dict[str, Any]:
    """The networks' ``pose`` table of the demo in ``folder`` (``{}``: no step marker).

    It comes from the preset stored in the first step marker; its ``seed`` is the training
    seed (absent: 0).
    """
    for step in STEPS:
        m = read_marker(folder, step)
        if m is not None:
            return _get(m, "preset", "pose") or {}
    return {}


def schedule_of(pose: dict[str, Any]) -> dict[str, Any]:
    """The training schedule of a demo preset's ``pose`` table: steps, rate and its drop."""
    return {k: pose[k] for k in SCHEDULE_KEYS if k in pose}


def record(folder: Path, command: list[str] | None = None) -> Path | None:
    """Record the finished demo run in ``folder`` as a result ``demo``.

    Args:
        folder: a demo output folder with ``summary.json``.
        command: the command that ran the demo (default: the one its seed reproduces).

    Returns:
        The result file (None when results are switched off).

    Raises:
        SystemExit: ``folder`` has no ``summary.json`` or its analysis step did not finish.
    """
    path = folder / SUMMARY
    if not path.is_file():
        raise SystemExit(f"{path} not found: give a folder that `freipose demo` finished")
    summary = json.loads(path.read_text(encoding="utf-8"))
    if "analysis" not in summary:
        raise SystemExit(f"{folder}: the demo has not finished (no analysis in {SUMMARY})")
    pose = marker_pose(folder)
    seed = int(pose.get("seed") or 0)
    figures = demo_figures(summary, step_seconds(folder, summary))
    finished = dt.datetime.fromtimestamp(path.stat().st_mtime, dt.timezone.utc)
    extra = {
        "seed": seed,
        "preset": summary.get("preset"),
        "init": summary.get("init"),
        "freipose_version": summary.get("freipose_version"),
        "schedule": schedule_of(pose),
        "folder": folder.name,
        "finished": finished.strftime("%Y-%m-%dT%H:%M:%SZ"),
    }
    cmd = command or ["freipose", "demo", "OUTDIR", "--seed", str(seed), "--threads", "2"]
    if summary.get("preset") not in (None, "small"):
        cmd += ["--preset", str(summary["preset"])]
    return write_result("demo", figures, command=cmd, extra=extra)


def main(argv: list[str] | None = None) -> int:
    """Run or read the demos and record them."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, nargs="+", default=[], help="run the demo with these")
    ap.add_argument("--work", type=Path, default=Path("bench/demo"), help="where runs go")
    ap.add_argument("--threads", type=int, default=2, help="freipose demo --threads")
    ap.add_argument("--from", dest="folders", type=Path, nargs="+", default=[],
                    help="finished demo folders to record")  # fmt: skip
    args = ap.parse_args(argv)
    if not args.seed and not args.folders:
        ap.error("give --seed S... (run the demo) or --from DIR... (record finished runs)")
    for seed in args.seed:
        out = args.work / f"demo_seed{seed}"
        cmd = ["freipose", "demo", str(out), "--seed", str(seed), "--threads", str(args.threads)]
        print("$ " + " ".join(cmd), flush=True)
        if subprocess.run(cmd, check=False).returncode != 0:
            raise SystemExit(f"freipose demo failed for seed {seed}")
        record(out, ["freipose", "demo", "OUTDIR", *cmd[3:]])
    for folder in args.folders:
        record(folder)
    return 0


if __name__ == "__main__":
    sys.exit(main())
