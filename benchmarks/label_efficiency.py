"""Learning curve: the labeled instants the voxel network needs, with and without unlabeled video.

Held-out synthetic rigs outside the shipped bases' training ranges (``freipose synth``):

* ``mouse_fisheye``: a mouse in a 250 mm box, 4 grayscale cameras with strong fisheye
  distortion, reflections in the walls, bedding, resting 60 % of the time;
* ``arc_piebald``: a piebald rat (a coat the randomised bases never see) filmed by 4
  cameras all on one side (the ``arc`` layout, never drawn by ``--randomize``).

Each rig is one recording (``--frames``, 100 s at 30 fps by default), split in time: two
blocks (40-50 % and 90-100 % of its frames) are held out for scoring, and a gap of
``--gap`` frames around them is unused. Each label budget (``--budgets``) draws its
instants at random (per seed) from the rest, and the unlabeled video is the rest too, all
of its frames (the same rig, animal and light; never the held-out blocks). The labels are
the generator's exact ones, and so is the scoring truth.

Every cell (rig, budget, seed, mode) trains the voxel network with ``freipose train``'s
config and is scored on the held-out instants against the exact truth (median JPE of P1
and P0 over the keypoints); the sanity references (the training labels' median pose at the
held-out centre and at the training centre, :mod:`freipose.nn.references`) come with each
budget. Modes: ``labels`` (labels only, ``--steps``), ``unlabeled`` (labels plus the
``[unlabeled]`` losses on clips from outside the held-out blocks, ``--steps``),
``labels_time`` (labels only, as many steps as fit in the wall time of the ``unlabeled``
cell: the comparison at equal wall time) and, with ``--ablate``, ``unlabeled-TERM`` (the
unlabeled cell without that term: its contribution). The cube centres of the unlabeled
frames are the true centre plus Gaussian noise of ``--center-noise`` mm, written as
``freipose predict`` writes them (``extra/center``): a detector of that precision.

Each cell writes its own result file (``OUT/cells/*.json``); a cell whose file exists is
skipped, so the script resumes where it stopped and a larger grid reuses a smaller one.
At the end the table of medians over seeds (with the min-max range) is printed and
recorded with ``benchmarks/_results.py`` (only the cells that ran).

Example (the 2-core CPU, one thread, the smallest useful grid; one command line)::

    OMP_NUM_THREADS=1 python benchmarks/label_efficiency.py --out bench/label_eff
        --rigs mouse_fisheye --budgets 10,50,200 --seeds 1 --steps 600
        --model grid_size=16 --model crop_size=64
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from _cli import freipose
from _results import write_result

RIGS: dict[str, list[str]] = {
    "mouse_fisheye": [
        "--animal", "mouse", "--arena-size", "250x250", "--cameras", "4", "--grayscale",
        "--lens", "fisheye", "--reflections", "0.3", "--rest-fraction", "0.6",
        "--floor", "bedding", "--fps", "30",
    ],
    "arc_piebald": [
        "--animal", "rat", "--cameras", "4", "--layout", "arc", "--appearance", "piebald",
        "--fps", "30",
    ],
}  # fmt: skip
MODES = ("labels", "unlabeled", "labels_time")
TERMS = ("multiview", "p0p1", "temporal", "equivariance", "bones")
# the contribution of each unlabeled term: the unlabeled cell without it (--ablate)
ABLATIONS = tuple(f"unlabeled-{t}" for t in TERMS)  # a term already off repeats "unlabeled"
# the terms that helped on mouse_fisheye at 25 labels (each left out in turn, --ablate):
# without multiview P1 5.42 mm, without p0p1 5.72, all five 6.35, labels only 6.52
UNLABELED_TABLE = {
    "clip_frames": 3,
    "share": 0.5,
    "weight_multiview": 0.0,
    "weight_p0p1": 0.0,
    "weight_temporal": 0.5,
    "weight_equivariance": 0.5,
    "weight_bones": 0.5,
}


def render(out: Path, rig: str, a: argparse.Namespace) -> Path:
    """The recording of ``rig`` (rendered once)."""
    lab = out / "rec" / rig
    if not (lab / "labels.h5").exists():
        freipose(["synth", str(lab), "--frames", str(a.frames), "--seed", "11",
                  "--size", a.size, *RIGS[rig]])  # fmt: skip
    return lab


def split(lab: Path, gap: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices (pool, held-out) of the recording's instants (see the docstring)."""
    from freipose.io.labels import read_labels_h5

    n = len(read_labels_h5(lab / "labels.h5"))
    f = np.arange(n)
    blocks = [(int(0.4 * n), int(0.5 * n)), (int(0.9 * n), n)]
    held = np.zeros(n, bool)
    near = np.zeros(n, bool)
    for a0, b0 in blocks:
        held |= (f >= a0) & (f < b0)
        near |= (f >= a0 - gap) & (f < b0 + gap)
    return f[~near], f[held]


def centers_file(unl: Path, pool: np.ndarray, noise: float) -> Path:
    """``centers.poses.h5``: the true centres plus detector noise of the frames of ``pool``.

    The other frames (the held-out blocks and their gaps) have none, so no clip is drawn
    from them.
    """
    from freipose.geometry.crops import label_centers
    from freipose.io.labels import read_labels_h5
    from freipose.io.poses import PoseData, write_poses_h5

    path = unl / "centers.poses.h5"
    if path.exists():
        return path
    labels = read_labels_h5(unl / "labels.h5")
    order = np.argsort(labels.frame_index)
    p3 = labels.points3d[order]
    rng = np.random.default_rng(0)
    centers = label_centers(p3) + rng.normal(0.0, noise, (len(p3), 3))
    centers[~np.isin(labels.frame_index[order], labels.frame_index[pool])] = np.nan
    data = PoseData(
        p3.astype(np.float32), np.ones(p3.shape[:2], np.float32), tuple(labels.keypoints),
        labels.frame_index[order].astype(np.int64), 30.0, (0.0, 0.0, 1.0),
        extra={"center": centers.astype(np.float32)},
    )  # fmt: skip
    write_poses_h5(data, path)
    return path


def write_config(run: Path, labels: Path, steps: int, seed: int, a: argparse.Namespace,
                 unl: tuple[Path, np.ndarray] | None, without: str = "") -> Path:  # fmt: skip
    """The training config of one cell (``without``: that unlabeled term weighted 0)."""
    run.mkdir(parents=True, exist_ok=True)
    text = (
        f'[data]\nlabels = "{labels}"\n\n[model]\npreset = "{a.preset}"\n'
        + "".join(f"{kv}\n" for kv in a.model)
        + "\n[schedule]\n"
        f"steps = {steps}\ncheckpoint_every = {steps}\neval_every = {steps}\n"
        f"log_every = 10\nseed = {seed}\n"
    )
    if unl is not None:
        table = {"sessions": [str(unl[0])], "centers": "poses",
                 "poses": [str(centers_file(*unl, a.center_noise))], **UNLABELED_TABLE}  # fmt: skip
        if without:
            table[f"weight_{without}"] = 0.0
        import tomli_w

        text += "\n" + tomli_w.dumps({"unlabeled": table})
    path = run / "train.toml"
    path.write_text(text, encoding="utf-8")
    return path


def budget_labels(lab: Path, pool: np.ndarray, budget: int, seed: int) -> Path:
    """The ``budget`` labeled instants of ``seed``, written beside the recording."""
    from freipose.io.labels import read_labels_h5, write_labels_h5

    path = lab / f"labels_b{budget}_s{seed}.h5"
    if not path.exists():
        pick = np.sort(np.random.default_rng([seed, budget]).choice(pool, budget, replace=False))
        write_labels_h5(read_labels_h5(lab / "labels.h5").select(pick), path)
    return path


def score(model_path: Path, lab: Path, held: np.ndarray, train: Path, n: int) -> dict[str, Any]:
    """Median JPE (mm) of P1, P0 and the references on ``n`` evenly spread held-out instants."""
    from freipose.io.labels import read_labels_h5
    from freipose.nn.checkpoint import load_checkpoint
    from freipose.nn.dataset import MultiViewDataset
    from freipose.nn.evaluate import jpe, predict_dataset
    from freipose.nn.references import reference_predictions

    idx = held[np.linspace(0, len(held) - 1, min(n, len(held))).round().astype(int)]
    model, _, _ = load_checkpoint(model_path)
    ds = MultiViewDataset(lab / "labels.h5")
    pred = predict_dataset(model, ds, idx)
    refs = reference_predictions(read_labels_h5(train).points3d, pred["gt"])
    out = {k: float(np.nanmedian(jpe(pred[k], pred["gt"]))) for k in ("P1", "P0")}
    out.update({k: float(np.nanmedian(jpe(v, pred["gt"]))) for k, v in refs.items()})
    return out


def train_seconds(run: Path) -> float:
    """Training wall time of a finished run (the last ``seconds`` of its log)."""
    import csv

    with (run / "log.csv").open() as f:
        rows = [r for r in csv.DictReader(f) if r.get("seconds")]
    return float(rows[-1]["seconds"])


def run_cell(out: Path, rig: str, budget: int, seed: int, mode: str, a: argparse.Namespace) -> None:
    """Train and score one cell unless its result file exists."""
    from freipose.nn.train import train_from_config

    cell = out / "cells" / f"{rig}_b{budget}_s{seed}_{mode}.json"
    if cell.exists():
        return
    lab = render(out, rig, a)
    pool, held = split(lab, a.gap)
    labels = budget_labels(lab, pool, budget, seed)
    steps = a.steps
    if mode == "labels_time":
        other = out / "cells" / f"{rig}_b{budget}_s{seed}_unlabeled.json"
        plain = out / "cells" / f"{rig}_b{budget}_s{seed}_labels.json"
        if not (other.exists() and plain.exists()):
            return
        per_step = json.loads(plain.read_text())["train_s"] / a.steps
        steps = max(1, int(round(json.loads(other.read_text())["train_s"] / per_step)))
    run = out / "runs" / cell.stem
    unl = (lab, pool) if mode.startswith("unlabeled") else None
    before = (run / "train.toml").read_text() if (run / "train.toml").exists() else None
    cfg = write_config(run, labels, steps, seed, a, unl, mode.partition("-")[2])
    if before is not None and before != cfg.read_text():
        raise SystemExit(f"{run} was trained with other settings; use another --out")
    t0 = time.perf_counter()
    model = run / "pose" / "model.pt"  # a finished run is reused, a stopped one resumed
    if not model.exists():
        resume = (run / "pose" / "checkpoint.pt").exists()
        model = train_from_config(cfg, run / "pose", progress=False, init=a.init, resume=resume)
    wall = time.perf_counter() - t0
    res = {"rig": rig, "budget": budget, "seed": seed, "mode": mode, "steps": steps,
           "train_s": train_seconds(run / "pose"), "wall_s": round(wall, 1),
           **score(model, lab, held, labels, a.eval_instants)}  # fmt: skip
    cell.parent.mkdir(parents=True, exist_ok=True)
    cell.write_text(json.dumps(res, indent=1) + "\n")
    print(f"{cell.stem}: P1 {res['P1']:.2f} mm, P0 {res['P0']:.2f} mm, {steps} steps, "
          f"{res['train_s']:.0f} s", flush=True)  # fmt: skip


def table(out: Path) -> dict[str, Any]:
    """Medians over seeds (min, max) of every (rig, budget, mode) that has cells."""
    cells = [json.loads(p.read_text()) for p in sorted((out / "cells").glob("*.json"))]
    groups: dict[tuple[str, int, str], list[dict[str, Any]]] = {}
    for c in cells:
        groups.setdefault((c["rig"], c["budget"], c["mode"]), []).append(c)
    figures: dict[str, Any] = {}
    print(f"{'rig':14s} {'labels':>6s} {'mode':22s} {'seeds':>5s} {'steps':>6s} "
          f"{'P1 median mm (min-max)':>24s} {'P0':>6s} {'median pose':>11s}")  # fmt: skip
    for (rig, budget, mode), cs in sorted(groups.items()):
        p1 = np.array([c["P1"] for c in cs])
        ref = np.median([c["median pose at held-out centre"] for c in cs])
        figures[f"{rig} {budget} {mode}"] = {
            "seeds": len(cs), "steps": int(np.median([c["steps"] for c in cs])),
            "P1_median_mm": float(np.median(p1)), "P1_min_mm": float(p1.min()),
            "P1_max_mm": float(p1.max()), "P0_median_mm": float(np.median([c["P0"] for c in cs])),
            "median_pose_held_out_centre_mm": float(ref),
            "train_s_median": float(np.median([c["train_s"] for c in cs])),
        }  # fmt: skip
        f = figures[f"{rig} {budget} {mode}"]
        print(f"{rig:14s} {budget:6d} {mode:22s} {len(cs):5d} {f['steps']:6d} "
              f"{f['P1_median_mm']:8.2f} ({f['P1_min_mm']:.2f}-{f['P1_max_mm']:.2f})"
              f"{'':5s} {f['P0_median_mm']:6.2f} {ref:11.2f}")  # fmt: skip
    return figures


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True, help="working folder (resumable)")
    p.add_argument("--rigs", default=",".join(RIGS), help=f"comma-separated of {list(RIGS)}")
    p.add_argument("--budgets", default="10,25,50,100,200", help="labeled instants")
    p.add_argument("--seeds", type=int, default=3, help="training seeds (0..N-1)")
    p.add_argument("--modes", default=",".join(MODES), help=f"comma-separated of {list(MODES)}")
    p.add_argument("--steps", type=int, default=300, help="training steps (equal-steps cells)")
    p.add_argument("--ablate", action="store_true",
                   help="also each unlabeled cell without one of its terms")  # fmt: skip
    p.add_argument("--preset", default="tiny", help="model preset")
    p.add_argument("--init", default="scratch", help="model.init (base, scratch or a file)")
    p.add_argument("--model", action="append", default=[], metavar="KEY=VALUE",
                   help="[model] line added to every config, e.g. grid_size=16")  # fmt: skip
    p.add_argument("--frames", type=int, default=3000, help="frames of each rig's recording")
    p.add_argument("--size", default="320x256", help="image size")
    p.add_argument("--gap", type=int, default=30, help="frames left out around held-out blocks")
    p.add_argument("--center-noise", type=float, default=5.0, help="mm, unlabeled centres")
    p.add_argument("--eval-instants", type=int, default=150, help="held-out instants scored")
    p.add_argument("--no-record", action="store_true", help="do not write a results file")
    return p


def main(argv: list[str] | None = None) -> int:
    a = _parser().parse_args(argv)
    rigs = [r for r in a.rigs.split(",") if r]
    unknown = [r for r in rigs if r not in RIGS]
    if unknown:
        raise SystemExit(f"unknown rigs {unknown}; choose from {list(RIGS)}")
    budgets = [int(b) for b in a.budgets.split(",")]
    modes = [m for m in MODES if m in a.modes.split(",")] + (list(ABLATIONS) if a.ablate else [])
    for rig in rigs:
        for budget in budgets:
            for seed in range(a.seeds):
                for mode in modes:
                    run_cell(a.out, rig, budget, seed, mode, a)
    figures = table(a.out)
    if not a.no_record and figures:
        write_result("label_efficiency", figures, extra={
            "steps": a.steps, "preset": a.preset, "model": a.model, "init": a.init,
            "frames": a.frames,
            "size": a.size, "gap": a.gap,
            "center_noise_mm": a.center_noise, "eval_instants": a.eval_instants,
            "unlabeled": UNLABELED_TABLE,
        })  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
