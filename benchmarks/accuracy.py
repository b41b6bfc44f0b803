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

Example (CPU, the ``small`` preset)::

    python benchmarks/accuracy.py --out bench/accuracy --preset small --steps 1500
    python benchmarks/accuracy.py --out bench/sweeps --steps 600 --experiments cameras,fraction

With one or two cameras, consider ``--set model.crop_fraction=1``: a keypoint outside a
view's crop then has no other view to cover it.

``--set TABLE.KEY=VALUE`` overrides the preset (as above); ``--kinds voxel`` and ``--kinds
baseline`` in two processes on the same ``--out`` use two cores, a third run with both
compares (trained models are reused).

``--init base,scratch`` trains every network twice at the same budget: fine-tuned from the
base models shipped in ``freipose/models`` (trained on seeds 10000+, see docs/models.md;
the sessions here use 101+ and 9001) and from random weights (``--init scratch``, the
default), and prints both tables and their ratio; the runs of each go to ``--out/<init>``.
``--base-dir DIR`` starts them from a copy of ``freipose/models`` instead (a fixed snapshot
while ``benchmarks/train_base.py`` keeps exporting). ``--rig-cameras N``, ``--rig-layout
NAME`` and ``--appearance COAT`` render every session (training and held-out: a lab's own
rig and animals) with that rig and coat, e.g. the ``arc`` layout and the ``piebald`` coat,
which the bases never saw; ``--eval-cameras N`` and ``--eval-appearance COAT`` render the
held-out session only with another rig or coat than the training sessions::

    python benchmarks/accuracy.py --out bench/outside --steps 300 --init base,scratch \
        --rig-layout arc --rig-cameras 5 --appearance piebald
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from _results import write_result

from freipose._compat import tomllib

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
    eval_scene: dict[str, Any] | None = None,
    scene: dict[str, Any] | None = None,
):
    """Synthetic training sessions (seeds 101, 102, ...) and the held-out one (seed 9001).

    Every session has its own jittered camera layout (``jitter_rig``). ``fps`` sets the
    spacing of the labeled instants: at the default 5 fps, 100 frames span 20 s of
    behaviour (like labels spread over a recording); at 50 fps they are 2 s of nearly one
    pose, which makes a held-out median an estimate from a single pose. ``scene`` holds
    ``SceneConfig`` settings of every session (a lab's own rig and animals: e.g. ``layout``,
    ``n_cameras``, ``appearance``), ``eval_scene`` those of the held-out session only (on
    top of ``scene``). Session folders are named after the settings.
    """
    from freipose.synth import SceneConfig, generate_session

    def suffix(settings: dict[str, Any]) -> str:
        return "".join(f"_{k}{v}" for k, v in sorted(settings.items()))

    common = dict(scene or {})
    train = []
    for i in range(n_train):
        cfg = SceneConfig(frames=frames, seed=101 + i, size=size, fps=fps, **common)
        out = root / f"train{i}{suffix(common)}"
        train.append(generate_session(out, cfg, progress=False).labels)
    extra = common | dict(eval_scene or {})
    cfg = SceneConfig(frames=eval_frames, seed=9001, size=size, fps=fps, **extra)
    name = "eval" + suffix(extra)
    ev = generate_session(root / name, cfg, progress=False).labels
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


def base_weights(base_dir: Path, kind: str) -> str:
    """The weights file of the ``kind`` base in a copy of ``freipose/models`` (``--base-dir``).

    Raises:
        SystemExit: the folder's ``bases.json`` lists no base of that kind.
    """
    from freipose.models import read_manifest

    for entry in read_manifest(base_dir / "bases.json"):
        if entry.get("kind") == kind and (base_dir / entry["file"]).is_file():
            return str(base_dir / entry["file"])
    raise SystemExit(
        f"--base-dir {base_dir}: expected a bases.json listing a {kind} base next to its "
        "weights file (a copy of freipose/models), found none"
    )


def run_pair(
    tag, base_cfg, train_lab, eval_lab, cameras, indices, out, device, log, kinds, base_dir=None
):
    """Train voxel + baseline on the same data/steps; evaluate both. Returns JPE arrays.

    Only the networks in ``kinds`` are trained; a network left out is still evaluated when
    its model already exists (another process trained it: ``--kinds``). With ``base_dir``
    a run of ``init = "base"`` starts from that folder's weights instead of the shipped ones.
    """
    from freipose.nn.checkpoint import load_checkpoint
    from freipose.nn.dataset import MultiViewDataset
    from freipose.nn.evaluate import jpe, predict_dataset
    from freipose.nn.train import train_pose
    from freipose.skeleton import load_skeleton

    skel = load_skeleton("rat")
    tr = MultiViewDataset(train_lab, root=Path("/"), cameras=cameras)
    ev = MultiViewDataset(eval_lab, root=Path("/"), cameras=cameras)
    res = {}
    for kind in ("voxel", "baseline"):
        if kind == "baseline" and cameras is not None and len(cameras) < 2:
            continue
        run_dir = out / tag / kind
        t0 = time.perf_counter()
        resume = (run_dir / "checkpoint.pt").exists()
        path = run_dir / "model.pt"
        if kind not in kinds and not path.exists():
            continue
        init = base_cfg.model.init
        if init == "base" and base_dir is not None:
            init = base_weights(base_dir, kind)
        cfg = dataclasses.replace(
            base_cfg, model=dataclasses.replace(base_cfg.model, kind=kind, init=init)
        )
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
    """Median, 30 % and 70 % percentiles of the labeled errors (inf: missing predictions)."""
    e = e[~np.isnan(e)]
    e = np.minimum(e, 1e12)
    q = np.percentile(e, [50, 30, 70])
    return tuple(float(v) if v < 1e12 else float("inf") for v in q)


NAN3 = (float("nan"),) * 3


def _parser() -> argparse.ArgumentParser:
    """The command line options."""
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
        "--init",
        default="scratch",
        help="starting weights, comma separated: scratch, base (the shipped base models) or "
        "both (base,scratch: the same budget twice, compared); runs go to --out/<init>",
    )
    ap.add_argument(
        "--base-dir",
        type=Path,
        default=None,
        help="with --init base: start from the bases in this copy of freipose/models (its "
        "bases.json and weights) instead of the installed ones, e.g. a snapshot taken while "
        "benchmarks/train_base.py keeps exporting",
    )
    ap.add_argument("--rig-cameras", type=int, default=0, help="cameras of every session's rig [7]")
    ap.add_argument(
        "--rig-layout",
        default="",
        help="layout of every session's rig (freipose synth --layout: ring, above, side, "
        "below, arc) [ring]",
    )
    ap.add_argument(
        "--appearance",
        default="",
        help="coat of every session's animal (freipose synth --appearance) [random]",
    )
    ap.add_argument("--eval-cameras", type=int, default=0, help="cameras of the held-out rig")
    ap.add_argument(
        "--eval-appearance", default="", help="coat of the held-out animal (hooded, albino, ...)"
    )
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
        help="override a [model], [schedule] or [augment] key of the preset (TOML value), e.g. "
        "--set model.unproject_levels=1; repeatable",
    )
    return ap


def _base_config(ap: argparse.ArgumentParser, args: argparse.Namespace) -> Any:
    """The training config of every run: the preset, the schedule options and ``--set``."""
    from freipose.nn.config import ConfigError, config_from_dict

    model_over: dict[str, Any] = {"preset": args.preset}
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
    augment: dict[str, Any] = {}
    for item in args.set:
        key, sep, value = item.partition("=")
        table, dot, name = key.strip().partition(".")
        if not sep or not dot or table not in ("model", "schedule", "augment"):
            ap.error(
                "--set expects model.KEY=VALUE, schedule.KEY=VALUE or augment.KEY=VALUE, "
                f"got {item!r}"
            )
        try:
            parsed = tomllib.loads(f"v = {value.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            ap.error(
                f"--set {item!r}: the value is not a TOML value (numbers, true/false, "
                f"quoted strings, [lists]), e.g. --set model.norm='\"batch\"'"
            )
        {"model": model_over, "schedule": sched, "augment": augment}[table][name] = parsed
    try:
        return config_from_dict({"model": model_over, "schedule": sched, "augment": augment})
    except ConfigError as exc:
        ap.error(f"--set: {exc}")


def _scenes(ap: argparse.ArgumentParser, args: argparse.Namespace) -> tuple[dict, dict]:
    """The ``SceneConfig`` settings of every session and of the held-out one only."""
    from freipose.synth import SceneConfig

    scene: dict[str, Any] = {}
    if args.rig_cameras:
        scene["n_cameras"] = args.rig_cameras
    if args.rig_layout:
        scene["layout"] = args.rig_layout
    if args.appearance:
        scene["appearance"] = args.appearance
    eval_scene: dict[str, Any] = {}
    if args.eval_cameras:
        eval_scene["n_cameras"] = args.eval_cameras
    if args.eval_appearance:
        eval_scene["appearance"] = args.eval_appearance
    try:
        SceneConfig(**scene)
        SceneConfig(**(scene | eval_scene))
    except ValueError as exc:
        ap.error(
            f"--rig-cameras, --rig-layout, --appearance, --eval-cameras or --eval-appearance: {exc}"
        )
    return scene, eval_scene


def _main_experiment(
    pair: Callable[..., dict[str, np.ndarray]], out: Path, keypoints: Any, log: Any
) -> dict[str, Any]:
    """All cameras, all training instants; writes the per-keypoint report to ``out/main``."""
    from freipose.nn.evaluate import write_report

    res = pair("main", None, None)
    write_report(out / "main", res, keypoints)
    main_res = {k: stats(v) for k, v in res.items()}
    v, b = main_res.get("voxel_P1", NAN3), main_res.get("baseline", NAN3)
    p0 = main_res.get("voxel_P0", NAN3)
    log("\nMAIN (all cameras, all instants): median JPE mm [30 %, 70 %]")
    log(f"  voxel P0   {p0[0]:7.2f}  [{p0[1]:.2f}, {p0[2]:.2f}]")
    log(f"  voxel P1   {v[0]:7.2f}  [{v[1]:.2f}, {v[2]:.2f}]")
    log(f"  baseline   {b[0]:7.2f}  [{b[1]:.2f}, {b[2]:.2f}]")
    log(
        f"  ratio voxel P1 / baseline = {v[0] / b[0]:.3f} (target <= 0.6); "
        f"P1 / P0 = {v[0] / p0[0]:.3f} (target < 1)"
    )
    return main_res


def _cameras_experiment(
    pair: Callable[..., dict[str, np.ndarray]], trials: int, log: Any
) -> dict[int, Any]:
    """The camera subsets of :data:`CAMERA_SETS`, ``trials`` subsets per number of cameras."""
    table = {}
    for n, sets in CAMERA_SETS.items():
        accs: dict[str, list] = {}
        for s in sets[:trials]:
            cams = [f"cam{i - 1}" for i in s]
            res = pair(f"cams{n}_{'-'.join(map(str, s))}", cams, None)
            for k, e in res.items():
                accs.setdefault(k, []).append(e.reshape(-1))
        table[n] = {k: stats(np.concatenate(v)) for k, v in accs.items()}
    log("\nCAMERAS: median JPE mm (voxel P1 / baseline)")
    for n, row in table.items():
        vx, b = row.get("voxel_P1", NAN3), row.get("baseline", NAN3)
        log(f"  {n} cams: voxel {vx[0]:7.2f}   baseline {b[0]:7.2f}")
    return table


def _fraction_experiment(
    pair: Callable[..., dict[str, np.ndarray]], n_train: int, trials: int, log: Any
) -> dict[float, Any]:
    """Random subsets of :data:`FRACTIONS` of the training instants, ``trials`` draws each."""
    table = {}
    rng = np.random.default_rng(0)
    all_idx = np.arange(n_train)
    for f in FRACTIONS:
        accs: dict[str, list] = {}
        for trial in range(trials if f < 1 else 1):
            idx = np.sort(rng.choice(all_idx, max(2, int(round(f * len(all_idx)))), replace=False))
            res = pair(f"frac{int(f * 100)}_{trial}", None, idx)
            for k, e in res.items():
                accs.setdefault(k, []).append(e.reshape(-1))
        table[f] = {k: stats(np.concatenate(v)) for k, v in accs.items()}
    log("\nLABEL FRACTION: median JPE mm (voxel P1 / baseline)")
    for f, row in table.items():
        vx, b = row.get("voxel_P1", NAN3), row.get("baseline", NAN3)
        log(f"  {int(f * 100):3d} %: voxel {vx[0]:7.2f}   baseline {b[0]:7.2f}")
    return table


class _Log:
    """Print a message and append it to ``log.txt``."""

    def __init__(self, path: Path):
        self.file = path.open("a")

    def __call__(self, msg: str) -> None:
        print(msg, flush=True)
        self.file.write(msg + "\n")
        self.file.flush()


def main(argv: list[str] | None = None) -> int:
    """Generate the sessions, run the experiments, print the tables and write the results."""
    ap = _parser()
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    torch_threads = int(os.environ.get("OMP_NUM_THREADS", "1"))

    import torch

    from freipose.io.labels import read_labels_h5

    torch.set_num_threads(torch_threads)
    from freipose.workers import keep_freed_memory

    keep_freed_memory()  # as the commands do (cli/_threads.py)
    kinds = {k.strip() for k in args.kinds.split(",") if k.strip()}
    if not kinds or not kinds <= {"voxel", "baseline"}:
        ap.error(f"--kinds takes voxel and/or baseline, got {args.kinds!r}")
    inits = [i.strip() for i in args.init.split(",") if i.strip()]
    if not inits or not set(inits) <= {"base", "scratch"}:
        ap.error(f"--init takes base and/or scratch, got {args.init!r}")
    if args.base_dir is not None and "base" in inits:
        for kind in kinds:
            base_weights(args.base_dir, kind)  # a wrong folder fails before any rendering
    base_cfg = _base_config(ap, args)
    scene, eval_scene = _scenes(ap, args)
    # the arguments are valid: only now the output folder
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    log = _Log(out / "log.txt")
    log(
        f"preset {args.preset}, {args.steps} steps x batch {args.batch_size}, "
        f"device {args.device}, "
        f"{torch.get_num_threads()} thread(s); model {base_cfg.model}"
    )
    t0 = time.perf_counter()
    train_paths, eval_path = make_sessions(
        out / "data",
        args.train_sessions,
        args.frames,
        args.eval_frames,
        tuple(args.size),
        args.fps,
        eval_scene,
        scene,
    )
    train_lab = merged_labels(train_paths)
    eval_lab = merged_labels([eval_path])
    log(
        f"data: {len(train_lab)} training instants ({args.train_sessions} sessions), "
        f"{len(eval_lab)} held-out instants; generated in {time.perf_counter() - t0:.0f} s"
    )
    results: dict = {"config": vars(args) | {"out": str(out)}, "init": {}}
    exps = [e.strip() for e in args.experiments.split(",") if e.strip()]
    all_idx = np.arange(len(train_lab))
    keypoints = read_labels_h5(eval_path).keypoints
    for init in inits:
        log(f"\n== init = {init} ==")
        cfg = dataclasses.replace(base_cfg, model=dataclasses.replace(base_cfg.model, init=init))
        run_out = out if init == "scratch" else out / init

        def pair(
            tag: str, cameras: list[str] | None, idx: np.ndarray | None, cfg=cfg, run_out=run_out
        ) -> dict:
            indices = all_idx if idx is None else idx
            return run_pair(
                tag,
                cfg,
                train_lab,
                eval_lab,
                cameras,
                indices,
                run_out,
                args.device,
                log,
                kinds,
                args.base_dir,
            )

        found: dict[str, Any] = {}
        if "main" in exps:
            found["main"] = _main_experiment(pair, run_out, keypoints, log)
        if "cameras" in exps:
            found["cameras"] = _cameras_experiment(pair, args.trials, log)
        if "fraction" in exps:
            table = _fraction_experiment(pair, len(train_lab), args.trials, log)
            found["fraction"] = {str(k): v for k, v in table.items()}
        _plots(run_out, {"experiments": found})
        results["init"][init] = found
    results["experiments"] = results["init"][inits[0]]
    _compare_inits(results["init"], log)
    figures = {init: _medians(found) for init, found in results["init"].items()}
    settings = {k: str(v) for k, v in vars(args).items() if k != "out"}
    write_result("accuracy", figures, extra=settings)
    (out / "results.json").write_text(json.dumps(results, indent=2, default=str))
    log(f"total {time.perf_counter() - t0:.0f} s; wrote {out / 'results.json'}")
    return 0


def _medians(table: Any) -> Any:
    """The table with each (median, 30 %, 70 %) triple replaced by its median."""
    if isinstance(table, dict):
        return {str(k): _medians(v) for k, v in table.items()}
    if isinstance(table, (list, tuple)) and table and not isinstance(table[0], (dict, list)):
        return table[0]
    return table


def _compare_inits(by_init: dict[str, dict[str, Any]], log: Any) -> None:
    """The main experiment's medians per starting weights, side by side."""
    rows = {i: r["main"] for i, r in by_init.items() if "main" in r}
    if len(rows) < 2:
        return
    keys = ("voxel_P0", "voxel_P1", "baseline")
    log("\nINIT (main experiment, equal budget): median JPE mm")
    log("  init      " + "".join(f"{k:>11s}" for k in keys))
    for init, row in rows.items():
        log(f"  {init:8s}  " + "".join(f"{row.get(k, NAN3)[0]:11.2f}" for k in keys))
    if {"base", "scratch"} <= set(rows):
        b, s = rows["base"], rows["scratch"]
        log(
            "  base / scratch: "
            + ", ".join(f"{k} {b.get(k, NAN3)[0] / s.get(k, NAN3)[0]:.3f}" for k in keys)
        )


def _plots(out: Path, results: dict) -> None:
    """``jpe_cameras.png`` and ``jpe_fraction.png`` of the sweeps that ran."""
    from freipose.io.figures import new_figure, save_figure

    for name, xlabel in (
        ("cameras", "number of cameras"),
        ("fraction", "fraction of labeled instants"),
    ):
        table = results["experiments"].get(name)
        if not table:
            continue
        xs = sorted(table, key=float)
        fig = new_figure((5, 4))
        ax = fig.subplots()
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
        save_figure(fig, out / f"jpe_{name}.png", dpi=120)


if __name__ == "__main__":
    raise SystemExit(main())
