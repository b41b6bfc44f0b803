"""Fine-tuning from the base models against training from scratch on real multi-view data.

Follows ``docs/own-data.md`` with FreiPose's own commands (run as subprocesses) on the
real 8-camera, 2-mouse SLEAP session of ``../shared/data/sleap-8cam-2mice`` (1280x1024,
frames 0-2 labeled, a 15-node mouse skeleton, aniposelib calibration):

1. ``freipose labels import --format sleap`` of ``min_session_frame_groups.slp`` (its
   cross-view instance groups; ``--instances``, default ``user``): one labeled instant per
   frame and mouse, keypoints seen in two or more views triangulated;
2. ``freipose labels split --by time --gap 1``: one labeled frame (both mice; the seed
   picks the last) is held out, the others are the training set. With three consecutive
   labeled frames no real gap is possible: the held-out frame is one video frame (33 ms)
   after the last training frame;
3. a train config per init (``[model] preset``, the cube sized from the training labels,
   no skeleton table: the labels' keypoint names); ``freipose train`` of the voxel network
   and ``--stage baseline`` with ``--init base`` and ``--init scratch`` at the same
   ``--steps``;
4. ``freipose eval`` with ``--baseline``: median JPE against the held-out triangulated
   labels, and the constant-pose references (the training labels' median pose at the
   held-out centre and at the training centre).

It adds a reference of its own, the pose of the training instant with the nearest centre
(a near-copy when the held-out frame follows a training frame), the networks' error on
their training frames (``freipose eval`` on the training labels: how well the budget fits
them), and measures each answer's 2D reprojection error against the held-out 2D labels
of the keypoints with a 3D label (the 3D labels are triangulated from these). ``--seeds
N`` repeats every training with N seeds. It prints one table and writes
``results.json`` into ``--out``. A finished step is skipped when run again on the same
``--out`` (trained models are reused; their wall time is kept in ``timings.json``).

Example (CPU, one thread)::

    OMP_NUM_THREADS=1 python benchmarks/real_finetune.py --out bench/real --steps 150 --seeds 3

``--map-window 0`` evaluates the same trained networks again with their 2D points from
the whole maps (``freipose eval --map-window``), into other folders of the same ``--out``
and ``results_map_window0.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from _results import write_result

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "sleap-8cam-2mice"
SLP = "min_session_frame_groups.slp"
KINDS = ("pose", "baseline")
METHODS = (
    ("voxel P1", "voxel_P1"),
    ("voxel P0", "voxel_P0"),
    ("baseline", "baseline"),
    ("reference at held-out centre", "median pose at held-out centre"),
    ("reference at training centre", "median pose at training centre"),
    ("nearest training instant", "nearest training instant"),
)
FRESH = "keypoint-specific output layers, which start fresh"
NETWORKS = ("voxel P1", "voxel P0", "baseline")
LABELS_ROW = "held-out 3D labels themselves"


class _Log:
    """Print a message and append it to ``log.txt``."""

    def __init__(self, path: Path):
        self.path = path

    def __call__(self, msg: str) -> None:
        print(msg, flush=True)
        with self.path.open("a", encoding="utf-8") as f:
            f.write(msg + "\n")


def freipose(args: list[str], log_file: Path) -> tuple[str, float]:
    """Run ``freipose ARGS`` in a subprocess; its output goes to ``log_file``.

    Returns:
        ``(output, seconds)``.

    Raises:
        SystemExit: the command failed (its output is printed).
    """
    cmd = [sys.executable, "-m", "freipose.cli.main", *args]
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True)
    secs = time.perf_counter() - t0
    out = res.stdout + res.stderr
    log_file.parent.mkdir(parents=True, exist_ok=True)
    log_file.write_text("$ freipose " + " ".join(args) + "\n" + out, encoding="utf-8")
    if res.returncode != 0:
        print(out, file=sys.stderr)
        raise SystemExit(f"freipose {' '.join(args)} failed (exit {res.returncode})")
    return out, secs


def prepare_labels(data: Path, out: Path, instances: str, log: _Log) -> tuple[Path, Path]:
    """Import the SLEAP session and split off its last labeled frame (``own-data.md`` 3-4)."""
    from freipose.io.labels import read_labels_h5

    lab = out / "labels"
    all_h5, train_h5, eval_h5 = lab / "all.h5", lab / "train.h5", lab / "eval.h5"
    if not all_h5.exists():
        args = ["labels", "import", "--format", "sleap", str(data / SLP)]
        freipose([*args, "--instances", instances, "-o", str(all_h5)], lab / "import.log")
    labels = read_labels_h5(all_h5)
    frames = np.unique(labels.frame_index)
    if len(frames) < 2:
        raise SystemExit(f"{all_h5}: {len(frames)} labeled frame(s); a time split needs two")
    if not eval_h5.exists():
        # one labeled frame of the session, with all its animals (+ a margin for rounding)
        share = 1.0 / len(frames) + 0.01
        args = ["labels", "split", str(all_h5), "--by", "time", "--gap", "1"]
        args += ["--eval", f"{share:.2f}", "-o", str(train_h5), str(eval_h5)]
        freipose(args, lab / "split.log")
    tr, ev = read_labels_h5(train_h5), read_labels_h5(eval_h5)
    shared = set(tr.frame_index.tolist()) & set(ev.frame_index.tolist())
    if shared or not len(tr) or not len(ev):
        raise SystemExit(
            f"the time split shares frames {sorted(shared)} between training and held-out "
            f"instants ({len(tr)} / {len(ev)}): it must hold out whole frames"
        )
    log(
        f"labels: {len(labels)} instants ({instances} instances) of frames "
        f"{frames.tolist()}, {len(labels.cameras)} cameras, {len(labels.keypoints)} keypoints; "
        f"training frames {sorted(set(tr.frame_index.tolist()))} ({len(tr)} instants), "
        f"held-out frames {sorted(set(ev.frame_index.tolist()))} ({len(ev)} instants)"
    )
    return train_h5, eval_h5


def write_config(path: Path, train_h5: Path, preset: str, steps: int, seed: int) -> None:
    """The train config of ``own-data.md`` step 5 (cube sized from the labels)."""
    every = max(1, min(50, steps))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(
        f'[data]\nlabels = "{train_h5.resolve()}"\n\n'
        f'[model]\npreset = "{preset}"\n\n'
        f"[schedule]\nsteps = {steps}\ncheckpoint_every = {every}\neval_every = {steps}\n"
        f"seed = {seed}\n",
        encoding="utf-8",
    )


def train_runs(
    out: Path, train_h5: Path, args: argparse.Namespace, init: str, seed: int, log: _Log
) -> dict[str, Any]:
    """Train the voxel network and the baseline from ``init``; reuse finished runs."""
    tag = f"{init}/seed{seed}"
    run = out / "runs" / tag
    cfg = run / "train.toml"
    write_config(cfg, train_h5, args.preset, args.steps, seed)
    timings_path = out / "timings.json"
    timings = json.loads(timings_path.read_text()) if timings_path.exists() else {}
    info: dict[str, Any] = {}
    for kind in KINDS:
        model = run / kind / "model.pt"
        key = f"{tag}/{kind}"
        if not model.exists():
            cmd = ["train", str(cfg), "--stage", kind, "--out", str(run / kind), "--init", init]
            cmd += ["--threads", str(args.threads)]
            if (run / kind / "checkpoint.pt").exists():
                cmd.append("--resume")
            _, secs = freipose(cmd, run / f"{kind}.log")
            timings[key] = secs
            timings_path.write_text(json.dumps(timings, indent=2))
        text = (run / f"{kind}.log").read_text(encoding="utf-8")
        cube = re.search(r"cube (\d+) mm from the training labels", text)
        base = re.search(r"starting from the base model '\w+' \(([\w.]+), (\d+) steps", text)
        info[kind] = {
            "seconds": timings.get(key, float("nan")),
            "fresh_keypoint_layers": FRESH in text,
            "cube_mm": float(cube.group(1)) if cube else None,
            "base": f"{base.group(1)} after {base.group(2)} steps" if base else None,
        }
        log(
            f"  [{tag}] {kind}: {timings.get(key, float('nan')):.0f} s"
            + (f"; cube {cube.group(1)} mm from the training labels" if cube else "")
            + ("; the log says the keypoint-specific layers start fresh" if FRESH in text else "")
        )
    return info


def run_eval(
    out: Path, eval_h5: Path, tag: str, train_h5: Path, sub: str = "", window: int | None = None
) -> dict[str, Any]:
    """``freipose eval`` of both networks of run ``tag``: the metrics.json it writes.

    ``sub``: a subfolder of the run's evaluation folder (another labels file); ``window``:
    ``--map-window`` (None: the checkpoints' own; another value evaluates into a
    ``map_window<W>`` subfolder).
    """
    run = out / "runs" / tag
    dest = out / "eval" / tag / sub if sub else out / "eval" / tag
    dest = dest if window is None else dest / f"map_window{window}"
    if not (dest / "metrics.json").exists():
        cmd = ["eval", str(run / "pose" / "model.pt"), str(eval_h5), "-o", str(dest)]
        cmd += ["--baseline", str(run / "baseline" / "model.pt"), "--train-labels", str(train_h5)]
        cmd += [] if window is None else ["--map-window", str(window)]
        freipose(cmd, dest / "eval.log")
    return json.loads((dest / "metrics.json").read_text())


def nearest_instant(train3d: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """The pose of the training instant with the nearest centre, at each held-out centre.

    Args:
        train3d: (M, K, 3) training 3D labels (mm), NaN where unlabeled.
        gt: (N, K, 3) held-out 3D labels (mm), NaN where unknown.

    Returns:
        (N, K, 3) the answers (mm), NaN where that training instant lacks the keypoint.
    """
    from freipose.geometry.crops import label_centers

    ct, ce = label_centers(train3d), label_centers(gt)
    near = np.argmin(np.linalg.norm(ce[:, None] - ct[None], axis=-1), axis=1)
    return train3d[near] - ct[near, None, :] + ce[:, None, :]


def reprojection_errors(
    out: Path, eval_h5: Path, train_h5: Path, tag: str, window: int | None = None
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Pixel distance of every answer's reprojection to the held-out 2D labels.

    The networks predict as in ``freipose eval`` (the cube on the label centre); the
    constant-pose references are those of ``freipose eval``; ``nearest training
    instant`` is :func:`nearest_instant`. ``labels`` is the held-out 3D labels' own
    reprojection error (their triangulation residual). ``window``: as in :func:`run_eval`.

    Returns:
        name -> (N, C, K) errors in px, NaN where a view has no 2D label; and the (N, K)
        JPE (mm) of the nearest training instant.
    """
    from freipose.geometry.triangulation import reprojection_errors as pixel_errors
    from freipose.io.labels import read_labels_h5
    from freipose.nn.config import InferenceOverrides
    from freipose.nn.evaluate import evaluate_checkpoints, jpe
    from freipose.nn.references import reference_predictions

    run = out / "runs" / tag
    ckpts = {"": run / "pose" / "model.pt", "baseline": run / "baseline" / "model.pt"}
    ev = evaluate_checkpoints(ckpts, eval_h5, overrides=InferenceOverrides(map_window=window))
    lab = read_labels_h5(eval_h5)
    answers = dict(ev.predictions)
    train3d = read_labels_h5(train_h5).points3d
    answers.update(reference_predictions(train3d, ev.gt))
    answers["nearest training instant"] = nearest_instant(train3d, ev.gt)
    answers["labels"] = ev.gt
    has3d = np.isfinite(ev.gt).all(-1)  # (N, K): the keypoints the JPE counts
    errs = {}
    for name, pts in answers.items():
        e = np.full(lab.points2d.shape[:3], np.nan)
        for i, sess in enumerate(lab.session):
            rig = lab.sessions[sess].calibration.subset(lab.cameras)
            e[i] = pixel_errors(pts[i], np.swapaxes(lab.points2d[i], 0, 1), rig).T  # (C, K)
        e[~np.broadcast_to(has3d[:, None, :], e.shape)] = np.nan
        errs[name] = e
    return errs, jpe(answers["nearest training instant"], ev.gt)


def _median(e: np.ndarray) -> tuple[float, int]:
    v = e[~np.isnan(e)]
    return (float(np.median(v)) if v.size else float("nan")), int(v.size)


def summarize(
    metrics: dict[str, Any],
    reproj: dict[str, np.ndarray],
    nearest_jpe: np.ndarray,
    fit: dict[str, Any],
) -> dict[str, Any]:
    """The rows of one run: median JPE (mm), n, median reprojection error (px), n.

    A network's row also has ``train_jpe_mm``, its median JPE on the training frames
    (``fit``: the metrics.json of ``freipose eval`` on the training labels).
    """
    rows = {}
    refs = dict(metrics.get("references", {}))
    jn, n = _median(nearest_jpe)
    refs["nearest training instant"] = {"median_mm": jn, "n": n}
    for label, key in METHODS:
        m = refs[key] if key in refs else metrics[key]["overall"]
        jpe, n = (m["median_mm"], m["n"]) if key in refs else (m["median"], m["n"])
        px, n2d = _median(reproj[key])
        rows[label] = {"jpe_mm": float(jpe), "n": int(n), "reproj_px": px, "n_2d": n2d}
        if key in fit:
            rows[label]["train_jpe_mm"] = float(fit[key]["overall"]["median"])
    px, n2d = _median(reproj["labels"])
    rows[LABELS_ROW] = {"jpe_mm": 0.0, "n": rows["voxel P1"]["n"], "reproj_px": px, "n_2d": n2d}
    return rows


def over_seeds(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The rows of one init over its seeds: the mean and each seed's figures."""
    rows = {}
    for label in runs[0]:
        per = [r[label] for r in runs]
        rows[label] = {
            "jpe_mm": float(np.mean([r["jpe_mm"] for r in per])),
            "jpe_mm_seeds": [r["jpe_mm"] for r in per],
            "n": per[0]["n"],
            "reproj_px": float(np.mean([r["reproj_px"] for r in per])),
            "reproj_px_seeds": [r["reproj_px"] for r in per],
            "n_2d": per[0]["n_2d"],
        }
        if "train_jpe_mm" in per[0]:
            rows[label]["train_jpe_mm"] = float(np.mean([r["train_jpe_mm"] for r in per]))
    return rows


def print_table(results: dict[str, Any], log: _Log) -> None:
    """The one table of the benchmark."""
    seeds = results["seeds"]
    log(
        f"\nREAL DATA ({results['data']}): {results['steps']} steps x batch 2 per network, "
        f"preset {results['preset']}, {results['instances']} instances, training seeds "
        f"{seeds}, map window {_window(results['map_window'])}; median JPE and 2D error on "
        "the held-out frame (the mean over the seeds, then each seed's JPE), fit: median JPE "
        "on the training frames"
    )
    head = f"{'JPE mm':>7s} {'n':>3s} {'2D px':>6s} {'n 2D':>4s} {'fit mm':>6s}"
    log(f"  {'init':8s} {'method':28s} {head}  seeds")
    for init, r in results["init"].items():
        for label, row in r["rows"].items():
            each = " / ".join(f"{v:.2f}" for v in row["jpe_mm_seeds"])
            fit = f"{row['train_jpe_mm']:6.2f}" if "train_jpe_mm" in row else " " * 6
            log(
                f"  {init:8s} {label:28s} {row['jpe_mm']:7.2f} {row['n']:3d} "
                f"{row['reproj_px']:6.2f} {row['n_2d']:4d} {fit}  "
                + (each if label in NETWORKS and len(seeds) > 1 else "")
            )
        t = r["train"]
        log(
            f"  {init:8s} wall time per run (mean): voxel {t['pose_seconds']:.0f} s, baseline "
            f"{t['baseline_seconds']:.0f} s; train log says the keypoint layers start fresh: "
            f"{t['fresh_keypoint_layers']}"
            + (f"; started from {', '.join(t['bases'])} (train logs)" if t["bases"] else "")
        )
    by = results["init"]
    if {"base", "scratch"} <= set(by):
        parts = []
        for label in NETWORKS:
            b, sc = by["base"]["rows"][label], by["scratch"]["rows"][label]
            wins = sum(x < y for x, y in zip(b["jpe_mm_seeds"], sc["jpe_mm_seeds"]))
            parts.append(
                f"{label} {b['jpe_mm'] / sc['jpe_mm']:.3f} (base better {wins}/{len(seeds)})"
            )
        log("  base / scratch (mean JPE): " + ", ".join(parts))
    log(
        "  truth: the held-out 3D labels are SLEAP points triangulated with the rig's own "
        "calibration (PROVENANCE: mean reprojection 4.35 px, median 3.02 px); 2D px: "
        "distance of each answer's reprojection to the held-out 2D SLEAP points of the "
        "keypoints with a 3D label. The skeleton (15 mouse nodes) is not the bases' "
        "12-keypoint rat: with init base every weight but the keypoint-specific layers comes "
        "from the base. The references look at no image: the training labels' median pose "
        "(freipose eval) and the pose of the training instant with the nearest centre (this "
        "script; here the same mouse one video frame earlier), placed at the held-out centre."
    )


def _window(value: int | None) -> str:
    """How the 2D maps were decoded, for the table's title."""
    if value is None:
        return "the networks' own"
    return "0 (whole maps)" if value == 0 else f"{value} px"


def _train_summary(trains: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Each seed's training facts and their means."""
    runs = list(trains.values())
    return {
        "pose_seconds": float(np.mean([t["pose"]["seconds"] for t in runs])),
        "baseline_seconds": float(np.mean([t["baseline"]["seconds"] for t in runs])),
        "fresh_keypoint_layers": all(t[k]["fresh_keypoint_layers"] for t in runs for k in KINDS),
        "bases": sorted({t[k]["base"] for t in runs for k in KINDS if t[k]["base"]}),
        "seeds": trains,
    }


def _record(args: argparse.Namespace, per_init: dict[str, list[dict[str, Any]]]) -> None:
    """One result per training seed: each init's held-out JPE and 2D error per method."""
    keys = ("jpe_mm", "reproj_px", "train_jpe_mm")
    settings = {"steps": args.steps, "preset": args.preset, "instances": args.instances,
                "map_window": args.map_window, "threads": args.threads}  # fmt: skip
    for seed in range(args.seeds):
        figures = {
            init: {
                label: {k: row[k] for k in keys if k in row} for label, row in runs[seed].items()
            }
            for init, runs in per_init.items()
        }
        write_result("real_finetune", figures, extra={"seed": seed, **settings})


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("bench/real_finetune"))
    ap.add_argument("--data", type=Path, default=DATA, help="the sleap-8cam-2mice folder")
    ap.add_argument("--steps", type=int, default=150, help="training steps of every network")
    ap.add_argument("--preset", default="small", help="[model] preset of the runs")
    ap.add_argument("--init", default="base,scratch", help="comma separated: base, scratch")
    ap.add_argument(
        "--seeds", type=int, default=1,
        help="training seeds per init and network ([schedule] seed 0, 1, ...): the spread of "
        "the figures over seeds",
    )  # fmt: skip
    ap.add_argument(
        "--instances", default="user", choices=("user", "predicted", "all"),
        help="SLEAP instances to import (the session's user instances are copies of its "
        "predictions)",
    )  # fmt: skip
    ap.add_argument(
        "--map-window", type=int,
        help="evaluate with freipose eval --map-window W (0: 2D points from the whole maps) "
        "[default: the networks' own, 3]",
    )  # fmt: skip
    ap.add_argument(
        "--threads", type=int, default=int(os.environ.get("OMP_NUM_THREADS", "1")),
        help="PyTorch threads of every run (freipose train --threads)",
    )  # fmt: skip
    return ap


def main(argv: list[str] | None = None) -> int:
    """Import, split, train, evaluate; print the table and write ``results.json``."""
    ap = _parser()
    args = ap.parse_args(argv)
    inits = [i.strip() for i in args.init.split(",") if i.strip()]
    if not inits or not set(inits) <= {"base", "scratch"}:
        ap.error(f"--init takes base and/or scratch, got {args.init!r}")
    if not (args.data / SLP).is_file():
        ap.error(f"{args.data / SLP} not found: give the sleap-8cam-2mice folder with --data")
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    log = _Log(out / "log.txt")
    t0 = time.perf_counter()
    train_h5, eval_h5 = prepare_labels(args.data, out, args.instances, log)
    seeds = list(range(args.seeds))
    results: dict[str, Any] = {
        "data": str(args.data), "steps": args.steps, "preset": args.preset,
        "instances": args.instances, "threads": args.threads, "seeds": seeds, "init": {},
        "map_window": args.map_window,
    }  # fmt: skip
    window = args.map_window
    per_init: dict[str, list[dict[str, Any]]] = {}
    for init in inits:
        runs, trains = [], {}
        for seed in seeds:
            train = train_runs(out, train_h5, args, init, seed, log)
            tag = f"{init}/seed{seed}"
            metrics = run_eval(out, eval_h5, tag, train_h5, window=window)
            fit = run_eval(out, train_h5, tag, train_h5, "training_frames", window)
            reproj, nearest = reprojection_errors(out, eval_h5, train_h5, tag, window)
            runs.append(summarize(metrics, reproj, nearest, fit))
            trains[f"seed{seed}"] = train
        results["init"][init] = {"rows": over_seeds(runs), "train": _train_summary(trains)}
        per_init[init] = runs
    print_table(results, log)
    _record(args, per_init)
    name = "results.json" if window is None else f"results_map_window{window}.json"
    (out / name).write_text(json.dumps(results, indent=2))
    log(f"total {time.perf_counter() - t0:.0f} s; wrote {out / name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
