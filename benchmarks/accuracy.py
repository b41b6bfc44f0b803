"""Accuracy of the voxel network against the triangulation baseline on synthetic sessions.

Reproduces the experiments of Section 5.4.3 of the method on synthetic data: training
sessions and a held-out evaluation session with another seed (other animal motion and, as
the default rig is jittered from the seed, another camera layout). Both networks are
trained on the same samples for the same number of steps, then evaluated by the joint
position error (JPE, mm) with the cube centred on the mean labeled 3D point.
Sessions are rendered at ``--fps`` (default 5), so their labeled instants spread over the
animal's behaviour instead of a second or two of nearly one pose.

Experiments (``--experiments``, comma separated):

* ``main``: all 7 cameras, all training instants; voxel P0 and P1 against the baseline.
* ``cameras``: the camera subsets of Table 5.1 (paper camera i = ``cam{i-1}``), 1 to 6
  cameras, ``--trials`` subsets each (the baseline cannot triangulate from one camera).
* ``fraction``: 10, 20, 30, 60, 80, 100 % of the training instants, ``--trials`` draws each.

Prints the tables and writes ``results.json``, ``jpe_cameras.png``, ``jpe_fraction.png`` and
the per-keypoint report of the main experiment (``main/``) into ``--out``.

Example (CPU, the ``small`` preset; the main experiment takes about 25 minutes on one
idle core, each sweep setting 5-10 minutes at 600 steps)::

    python benchmarks/accuracy.py --out bench/accuracy --preset small --steps 1500
    python benchmarks/accuracy.py --out bench/sweeps --steps 600 --experiments cameras,fraction

Measured 2026-11-22 (``small`` preset: stride-4 unprojected features, crops of the middle
60 % of the cube, refinement trained from 20 % of the steps, P0 fusion weight per keypoint;
1500 steps x batch 2, CPU, one thread of the 2-core machine with another training on the
other core; 3 training sessions of 100 instants, held-out session of 60 instants with another
seed and camera layout), ``python benchmarks/accuracy.py --steps 1500 --experiments main``:

    training seed 0: voxel P0 4.25 mm, P1 3.90 mm [30 %: 2.50, 70 %: 6.20]; baseline 6.84 mm
                     [4.13, 12.69]: P1 / baseline 0.570, P1 / P0 0.917
    training seed 1 (``--set schedule.seed=1``): P0 5.00, P1 3.93 [2.51, 6.53]; baseline
                     7.53 [4.38, 14.59]: P1 / baseline 0.522 (0.574 against seed 0's
                     baseline), P1 / P0 0.785

The voxel network beats the baseline on every keypoint (paws 4.5-8.4 mm vs 9.5-21 mm, head
2-3 mm vs 2-4 mm). What each change did (seed 0, same data, same baseline 6.84 mm; P0 / P1):
the previous preset 5.30 / 4.96; stride-4 unprojected features 4.63 / 4.99 (the refinement,
trained for only the last half, then made P1 worse than P0); refinement from 20 % of the
steps 4.57 / 4.63; crops of the middle 70 % of the cube 4.58 / 4.19, with per-keypoint fusion
weights 4.44 / 4.09 (seed 1: 4.48 / 4.01); middle 60 % 4.25 / 3.90. The baseline crops the
whole cube (with 70 % crops it got worse: 7.88 mm, keypoints outside a crop are lost to it).

The sweeps were measured with the previous preset at 600 steps (one subset / draw per
setting; median JPE voxel P1 vs baseline, mm): cameras 1: 20.1 vs - (cannot triangulate), 2:
12.6 vs 21.2, 3: 11.7 vs 22.5, 4: 8.9 vs 18.3, 5: 8.3 vs 16.7, 6: 8.8 vs 16.4; labeled
fraction 10 %: 8.9 vs 14.9, 20 %: 9.8 vs 15.8, 30 %: 8.3 vs 14.9, 60 %: 7.6 vs 19.3, 80 %: 7.2
vs 16.3, 100 %: 8.1 vs 18.7. At 600 steps the baseline is under-trained (6.84 mm at 1500
steps), so these ratios (~0.5) flatter the voxel network; one draw per setting makes them
noisy. With one or two cameras, consider ``--set model.crop_fraction=1``: a keypoint outside
a view's crop then has no other view to cover it.

``--set TABLE.KEY=VALUE`` overrides the preset (as above); ``--kinds voxel`` and ``--kinds
baseline`` in two processes on the same ``--out`` use two cores, a third run with both
compares (trained models are reused).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import sys
import time
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

import numpy as np

CAMERA_SETS = {
    1: [[1], [5], [7]],
    2: [[1, 5], [1, 7], [1, 3]],
    3: [[1, 5, 7], [1, 3, 5], [4, 5, 7]],
    4: [[1, 3, 4, 5], [1, 3, 4, 7], [1, 4, 5, 7]],
    5: [[1, 3, 4, 5, 7], [2, 6, 4, 5, 7], [1, 3, 4, 5, 6]],
    6: [[1, 2, 3, 4, 5, 7], [1, 2, 3, 4, 5, 6], [1, 2, 4, 5, 6, 7]],
}
FRACTIONS = [0.1, 0.2, 0.3, 0.6, 0.8, 1.0]


def make_sessions(
    root: Path,
    n_train: int,
    frames: int,
    eval_frames: int,
    size: tuple[int, int],
    fps: float = 5.0,
):
    """Synthetic training sessions (seeds 101, 102, ...) and the held-out one (seed 9001).

    Every session has its own jittered camera layout (``jitter_rig``). ``fps`` sets the
    spacing of the labeled instants: at the default 5 fps, 100 frames span 20 s of
    behaviour (like labels spread over a recording); at 50 fps they are 2 s of nearly one
    pose, which makes a held-out median an estimate from a single pose.
    """
    from freipose.synth import SceneConfig, generate_session

    train = []
    for i in range(n_train):
        cfg = SceneConfig(frames=frames, seed=101 + i, size=size, fps=fps)
        train.append(generate_session(root / f"train{i}", cfg, progress=False).labels)
    cfg = SceneConfig(frames=eval_frames, seed=9001, size=size, fps=fps)
    ev = generate_session(root / "eval", cfg, progress=False).labels
    return train, ev


def merged_labels(paths: list[Path]):
    """Concatenate labels of several sessions (video paths made absolute)."""
    from freipose.io.labels import LabelSet, SessionInfo, read_labels_h5

    parts = [read_labels_h5(p) for p in paths]
    sessions = {}
    for p, lab in zip(paths, parts):
        for info in lab.sessions.values():
            vids = {c: str((p.parent / v).resolve()) for c, v in info.videos.items()}
            sessions[f"{p.parent.name}"] = SessionInfo(info.calibration, vids, info.fps)
    return LabelSet(
        session=np.concatenate([[p.parent.name] * len(lab) for p, lab in zip(paths, parts)]),
        frame_index=np.concatenate([lab.frame_index for lab in parts]),
        points2d=np.concatenate([lab.points2d for lab in parts]),
        points3d=np.concatenate([lab.points3d for lab in parts]),
        cameras=parts[0].cameras,
        keypoints=parts[0].keypoints,
        sessions=sessions,
        visible2d=np.concatenate([lab.visible2d for lab in parts]),
    )


def run_pair(tag, base_cfg, train_lab, eval_lab, cameras, indices, out, device, log, kinds):
    """Train voxel + baseline on the same data/steps; evaluate both. Returns JPE arrays.

    Only the networks in ``kinds`` are trained; a network left out is still evaluated when
    its model already exists (another process trained it: ``--kinds``)."""
    from freipose.nn.dataset import MultiViewDataset
    from freipose.nn.evaluate import jpe, predict_dataset
    from freipose.nn.checkpoint import load_checkpoint
    from freipose.nn.train import train_pose
    from freipose.skeleton import load_skeleton

    skel = load_skeleton("rat")
    tr = MultiViewDataset(train_lab, root=Path("/"), cameras=cameras)
    ev = MultiViewDataset(eval_lab, root=Path("/"), cameras=cameras)
    res = {}
    for kind in ("voxel", "baseline"):
        if kind == "baseline" and cameras is not None and len(cameras) < 2:
            continue
        cfg = dataclasses.replace(base_cfg, model=dataclasses.replace(base_cfg.model, kind=kind))
        run_dir = out / tag / kind
        t0 = time.perf_counter()
        resume = (run_dir / "checkpoint.pt").exists()
        path = run_dir / "model.pt"
        if kind not in kinds and not path.exists():
            continue
        if not path.exists():
            path = train_pose(
                cfg,
                run_dir,
                tr,
                skel,
                None,
                train_indices=indices,
                resume=resume,
                device=device,
                progress=sys.stderr.isatty(),
            )
        model, _, _ = load_checkpoint(path, device)
        pred = predict_dataset(model, ev, batch_size=4)
        if kind == "voxel":
            res["voxel_P0"] = jpe(pred["P0"], pred["gt"])
            res["voxel_P1"] = jpe(pred["P1"], pred["gt"])
        else:
            res["baseline"] = jpe(pred["P1"], pred["gt"])
        log(
            f"  [{tag}] {kind}: trained+evaluated in {time.perf_counter() - t0:.0f} s; "
            + ", ".join(f"{k} median {np.nanmedian(v):.2f} mm" for k, v in res.items())
        )
        # a systematic offset (mean signed error, mm) points at a geometry/convention bug
        bias = np.nanmean(pred["P1"] - pred["gt"], axis=(0, 1))
        log(f"  [{tag}] {kind}: mean signed error x, y, z = {np.round(bias, 2).tolist()} mm")
    return res


def stats(e: np.ndarray) -> tuple[float, float, float]:
    e = e[~np.isnan(e)]
    e = np.minimum(e, 1e12)
    q = np.percentile(e, [50, 30, 70])
    return tuple(float(v) if v < 1e12 else float("inf") for v in q)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("bench/accuracy"))
    ap.add_argument("--preset", default="small")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--batch-size", type=int, default=2)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--experiments", default="main")
    ap.add_argument("--trials", type=int, default=1, help="subsets/draws per setting (paper: 3)")
    ap.add_argument("--train-sessions", type=int, default=3)
    ap.add_argument("--frames", type=int, default=100, help="frames per training session")
    ap.add_argument("--eval-frames", type=int, default=60)
    ap.add_argument(
        "--fps", type=float, default=5.0, help="frame rate of the sessions (label spacing)"
    )
    ap.add_argument("--size", type=int, nargs=2, default=(320, 256), help="image width height")
    ap.add_argument("--cube-size", type=float, default=None, help="override model.cube_size (mm)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument(
        "--kinds",
        default="voxel,baseline",
        help="networks to train (comma separated): run one process with voxel and one with "
        "baseline on the same --out to use two cores, then once more with both to print the "
        "comparison (trained models are reused)",
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="TABLE.KEY=VALUE",
        help="override a [model] or [schedule] key of the preset (TOML value), e.g. "
        "--set model.unproject_levels=1; repeatable",
    )
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    torch_threads = int(os.environ.get("OMP_NUM_THREADS", "1"))

    import torch

    from freipose.io.labels import read_labels_h5
    from freipose.nn.config import ConfigError, config_from_dict
    from freipose.nn.evaluate import write_report

    torch.set_num_threads(torch_threads)
    model_over = {"preset": args.preset}
    if args.cube_size:
        model_over["cube_size"] = args.cube_size
    sched = {
        "steps": args.steps,
        "batch_size": args.batch_size,
        "lr": args.lr,
        "lr_decay_steps": max(1, int(args.steps * 2 / 3)),
        "checkpoint_every": 100,
        "log_every": 10,
    }
    for item in args.set:
        key, sep, value = item.partition("=")
        table, dot, name = key.strip().partition(".")
        if not sep or not dot or table not in ("model", "schedule"):
            ap.error(f"--set expects model.KEY=VALUE or schedule.KEY=VALUE, got {item!r}")
        try:
            parsed = tomllib.loads(f"v = {value.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            ap.error(
                f"--set {item!r}: the value is not a TOML value (numbers, true/false, "
                f"quoted strings, [lists]), e.g. --set model.norm='\"batch\"'"
            )
        (model_over if table == "model" else sched)[name] = parsed
    kinds = {k.strip() for k in args.kinds.split(",") if k.strip()}
    if not kinds or not kinds <= {"voxel", "baseline"}:
        ap.error(f"--kinds takes voxel and/or baseline, got {args.kinds!r}")
    try:
        base_cfg = config_from_dict({"model": model_over, "schedule": sched})
    except ConfigError as exc:
        ap.error(f"--set: {exc}")
    # the arguments are valid: only now the output folder
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    logf = (out / "log.txt").open("a")

    def log(msg: str) -> None:
        print(msg, flush=True)
        logf.write(msg + "\n")
        logf.flush()

    log(
        f"preset {args.preset}, {args.steps} steps x batch {args.batch_size}, "
        f"device {args.device}, "
        f"{torch.get_num_threads()} thread(s); model {base_cfg.model}"
    )
    t0 = time.perf_counter()
    train_paths, eval_path = make_sessions(
        out / "data", args.train_sessions, args.frames, args.eval_frames, tuple(args.size), args.fps
    )
    train_lab = merged_labels(train_paths)
    eval_lab = merged_labels([eval_path])
    log(
        f"data: {len(train_lab)} training instants ({args.train_sessions} sessions), "
        f"{len(eval_lab)} held-out instants; generated in {time.perf_counter() - t0:.0f} s"
    )
    results: dict = {"config": vars(args) | {"out": str(out)}, "experiments": {}}
    exps = [e.strip() for e in args.experiments.split(",") if e.strip()]
    all_idx = np.arange(len(train_lab))
    nan3 = (float("nan"),) * 3
    if "main" in exps:
        res = run_pair(
            "main", base_cfg, train_lab, eval_lab, None, all_idx, out, args.device, log, kinds
        )
        write_report(out / "main", res, read_labels_h5(eval_path).keypoints)
        results["experiments"]["main"] = {k: stats(v) for k, v in res.items()}
        main_res = results["experiments"]["main"]
        v, b = main_res.get("voxel_P1", nan3), main_res.get("baseline", nan3)
        p0 = main_res.get("voxel_P0", nan3)
        log("\nMAIN (7 cameras, all instants): median JPE mm [30 %, 70 %]")
        log(f"  voxel P0   {p0[0]:7.2f}  [{p0[1]:.2f}, {p0[2]:.2f}]")
        log(f"  voxel P1   {v[0]:7.2f}  [{v[1]:.2f}, {v[2]:.2f}]")
        log(f"  baseline   {b[0]:7.2f}  [{b[1]:.2f}, {b[2]:.2f}]")
        log(
            f"  ratio voxel P1 / baseline = {v[0] / b[0]:.3f} (target <= 0.6); "
            f"P1 / P0 = {v[0] / p0[0]:.3f} (target < 1)"
        )
    if "cameras" in exps:
        table = {}
        for n, sets in CAMERA_SETS.items():
            accs: dict[str, list] = {}
            for s in sets[: args.trials]:
                cams = [f"cam{i - 1}" for i in s]
                res = run_pair(
                    f"cams{n}_{'-'.join(map(str, s))}",
                    base_cfg,
                    train_lab,
                    eval_lab,
                    cams,
                    all_idx,
                    out,
                    args.device,
                    log,
                    kinds,
                )
                for k, e in res.items():
                    accs.setdefault(k, []).append(e.reshape(-1))
            table[n] = {k: stats(np.concatenate(v)) for k, v in accs.items()}
        results["experiments"]["cameras"] = table
        log("\nCAMERAS: median JPE mm (voxel P1 / baseline)")
        for n, row in table.items():
            vx, b = row.get("voxel_P1", nan3), row.get("baseline", nan3)
            log(f"  {n} cams: voxel {vx[0]:7.2f}   baseline {b[0]:7.2f}")
    if "fraction" in exps:
        table = {}
        rng = np.random.default_rng(0)
        for f in FRACTIONS:
            accs = {}
            for trial in range(args.trials if f < 1 else 1):
                idx = np.sort(
                    rng.choice(all_idx, max(2, int(round(f * len(all_idx)))), replace=False)
                )
                res = run_pair(
                    f"frac{int(f * 100)}_{trial}",
                    base_cfg,
                    train_lab,
                    eval_lab,
                    None,
                    idx,
                    out,
                    args.device,
                    log,
                    kinds,
                )
                for k, e in res.items():
                    accs.setdefault(k, []).append(e.reshape(-1))
            table[f] = {k: stats(np.concatenate(v)) for k, v in accs.items()}
        results["experiments"]["fraction"] = {str(k): v for k, v in table.items()}
        log("\nLABEL FRACTION: median JPE mm (voxel P1 / baseline)")
        for f, row in table.items():
            vx, b = row.get("voxel_P1", nan3), row.get("baseline", nan3)
            log(f"  {int(f * 100):3d} %: voxel {vx[0]:7.2f}   baseline {b[0]:7.2f}")
    _plots(out, results)
    (out / "results.json").write_text(json.dumps(results, indent=2, default=str))
    log(f"total {time.perf_counter() - t0:.0f} s; wrote {out / 'results.json'}")
    return 0


def _plots(out: Path, results: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for name, xlabel in (
        ("cameras", "number of cameras"),
        ("fraction", "fraction of labeled instants"),
    ):
        table = results["experiments"].get(name)
        if not table:
            continue
        xs = sorted(table, key=float)
        fig, ax = plt.subplots(figsize=(5, 4))
        for key, label in (
            ("voxel_P1", "FreiPose (voxel, P1)"),
            ("baseline", "2D + triangulation"),
        ):
            pts = [(float(x), table[x][key]) for x in xs if key in table[x]]
            if not pts:
                continue
            x = np.array([p[0] for p in pts])
            q = np.array([p[1] for p in pts], dtype=float)
            q[~np.isfinite(q)] = np.nan
            ax.plot(x, q[:, 0], "o-", label=label)
            ax.fill_between(x, q[:, 1], q[:, 2], alpha=0.2)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("median JPE (mm), 30-70 %")
        ax.legend()
        ax.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(out / f"jpe_{name}.png", dpi=120)
        plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
