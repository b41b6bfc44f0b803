"""The own-rig path of ``docs/own-data.md`` on a synthetic mouse rig, timed and scored.

Scored against the held-out labels and against the exact truth.

The rig has what a lab's own rig has (issue #21): a mouse in a 250 mm box, 4 grayscale
cameras with strong fisheye distortion, reflections of the mouse in the walls, bedding, a
mouse resting 60 % of the time, and labels as another tool writes them (one SLEAP file
per camera of predicted instances). The commands are FreiPose's, run in this process as
on the command line, in the order of the document:

1. ``freipose synth`` (the recording, its board videos and the per-camera label files);
2. ``freipose calib`` with ``--origin-frame 0``;
3. ``freipose labels import --format sleap --instances predicted``;
4. ``freipose labels split --by time`` (``--blocks`` held-out blocks, ``--gap`` frames);
5. ``freipose train`` of the voxel network and ``--stage baseline`` at the same
   ``--steps``, from the shipped base models;
6. ``freipose eval`` with ``--baseline``: median and mean JPE against the held-out labels,
   the constant-pose references and the paired comparisons.

The held-out labels are another tool's predictions triangulated with FreiPose's
calibration, so they carry that tool's error (printed: their distance from the truth). The
benchmark also scores every answer against the exact truth of the generator, mapped into
the calibration's world frame by the similarity that best maps the true keypoints onto the
imported labels of all frames, on the keypoints the held-out labels have and on every
keypoint (the label tool leaves out the ones it cannot see, such as a hind paw under the
resting mouse, so only the truth can score a network there). ``--seeds N`` repeats the
training with N seeds (the data stay); a finished step is skipped when run again on the
same ``--out``.

Example (the 2-core CPU, one thread, as the issue's budget)::

    OMP_NUM_THREADS=1 python benchmarks/own_rig.py --out bench/own_rig --seeds 2
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from _cli import step as run_step
from _results import write_result

RIG = [
    "--animal", "mouse", "--arena-size", "250x250", "--cameras", "4", "--grayscale",
    "--lens", "fisheye", "--reflections", "0.3", "--rest-fraction", "0.6",
    "--floor", "bedding", "--label-files", "sleap", "--fps", "30",
    "--calibration-video", "--calibration-frames", "100",
]  # fmt: skip
NETWORKS = ("voxel_P1", "voxel_P0", "baseline")
AT_HELD_OUT = "median pose at held-out centre"
AT_TRAINING = "median pose at training centre"


def step(done: Path, args: list[str], times: dict[str, float], name: str) -> None:
    """Run a command unless its output ``done`` exists (then its earlier time is kept)."""
    seconds = run_step(done, args)
    if seconds is not None:
        times[name] = round(seconds, 1)


def prepare(out: Path, a: argparse.Namespace, times: dict[str, float]) -> None:
    """Steps 1-4: the recording, the calibration, the imported labels and the split."""
    rec = out / "rec" / "mouse1"
    size = ["--size", a.size, "--frames", str(a.frames), "--seed", str(a.data_seed)]
    step(rec / "labels.h5", ["synth", str(rec), *RIG, *size], times, "synth")
    cal = out / "calibration.toml"
    boards = sorted(str(p) for p in (rec / "calibration").glob("cam*.mp4"))
    board = ["--board", str(rec / "calibration" / "board.toml"), "--origin-frame", "0"]
    step(cal, ["calib", *boards, *board, "-o", str(cal)], times, "calib")
    lab = out / "labels"
    imp = ["labels", "import", "--format", "sleap", str(rec), "--instances", "predicted"]
    step(lab / "all.h5", [*imp, "--calibration", str(cal), "-o", str(lab / "all.h5")],
         times, "import")  # fmt: skip
    split = ["labels", "split", str(lab / "all.h5"), "--by", "time", "--gap", str(a.gap)]
    split += ["--eval", "0.25", "--blocks", str(a.blocks)]
    step(lab / "eval.h5", [*split, "-o", str(lab / "train.h5"), str(lab / "eval.h5")],
         times, "split")  # fmt: skip


def write_config(path: Path, labels: Path, a: argparse.Namespace, seed: int) -> None:
    """The train config of ``own-data.md`` step 5 at ``--steps`` and a training seed."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(
        f'[data]\nlabels = "{labels / "train.h5"}"\neval_labels = "{labels / "eval.h5"}"\n'
        f'skeleton = "rat"\n\n[model]\npreset = "{a.preset}"\n\n[schedule]\n'
        f"steps = {a.steps}\ncheckpoint_every = {a.steps}\neval_every = {a.steps}\n"
        f"seed = {seed}\n" + "".join(f"{kv}\n" for kv in a.schedule),
        encoding="utf-8",
    )


def train_and_eval(out: Path, run: Path, a: argparse.Namespace, seed: int) -> dict[str, float]:
    """Steps 5-6 for one training seed; returns the commands' wall times."""
    times: dict[str, float] = {}
    cfg = run / "train.toml"
    write_config(cfg, out / "labels", a, seed)
    init = ["--init", a.init]
    step(run / "pose" / "model.pt", ["train", str(cfg), "--out", str(run / "pose"), *init],
         times, "train voxel")  # fmt: skip
    base = ["train", str(cfg), "--stage", "baseline", "--out", str(run / "baseline"), *init]
    step(run / "baseline" / "model.pt", base, times, "train baseline")
    ev = ["eval", str(run / "pose" / "model.pt"), str(out / "labels" / "eval.h5")]
    ev += ["--baseline", str(run / "baseline" / "model.pt"), "-o", str(run / "eval")]
    step(run / "eval" / "metrics.json", ev, times, "eval")
    return times


def truth_alignment(out: Path) -> tuple[float, np.ndarray, np.ndarray, float]:
    """Similarity ``(s, R, t)`` from the true world into the calibration's, and more.

    The fourth value is the imported labels' median distance from the mapped truth (the
    label tool's error, mm).
    """
    from freipose.geometry.alignment import align_similarity
    from freipose.io.labels import read_labels_h5

    lab = read_labels_h5(out / "labels" / "all.h5")
    true = true_points(out, lab.frame_index)
    A, B = true.reshape(-1, 3), lab.points3d.reshape(-1, 3)
    ok = np.isfinite(A).all(1) & np.isfinite(B).all(1)
    s, R, t = align_similarity(A[ok], B[ok])
    return s, R, t, float(np.median(np.linalg.norm(s * A[ok] @ R.T + t - B[ok], axis=1)))


def true_points(out: Path, frames: np.ndarray) -> np.ndarray:
    """(N, K, 3) the generator's true keypoints (true world) of video frames ``frames``."""
    from freipose.io.labels import read_labels_h5

    truth = read_labels_h5(out / "rec" / "mouse1" / "labels.h5")
    row = {int(f): i for i, f in enumerate(truth.frame_index)}
    return truth.points3d[[row[int(f)] for f in frames]]


def against_truth(out: Path, run: Path, align: tuple) -> dict[str, Any]:
    """Every answer's JPE against the mapped truth: on the labeled keypoints and on all.

    Returns:
        ``truth`` (the keypoints the held-out labels have), ``truth_all`` (every keypoint,
        also those hidden from the label tool), each as :func:`_scores` gives, and
        ``labels_vs_truth`` (median mm), ``keypoints`` and ``labeled_share`` (per keypoint,
        the share of held-out instants the labels have it).
    """
    from freipose.io.labels import read_labels_h5
    from freipose.nn.dataset import MultiViewDataset
    from freipose.nn.evaluate import evaluate_checkpoints, usable_indices

    s, R, t, _ = align
    nets = {"": run / "pose" / "model.pt", "baseline": run / "baseline" / "model.pt"}
    held_path = out / "labels" / "eval.h5"
    ev = evaluate_checkpoints(nets, held_path)
    held = read_labels_h5(held_path)
    rows = usable_indices(MultiViewDataset(held, root=held_path.resolve().parent))
    every = s * true_points(out, held.frame_index[rows]) @ R.T + t
    labeled = np.where(np.isnan(ev.gt), np.nan, every)
    train = read_labels_h5(out / "labels" / "train.h5").points3d
    return {
        "truth": _scores(ev.predictions, labeled, train),
        "truth_all": _scores(ev.predictions, every, train),
        "keypoints": list(ev.keypoints),
        "labeled_share": np.isfinite(labeled).all(-1).mean(0).tolist(),
        "labels_vs_truth": float(np.nanmedian(np.linalg.norm(ev.gt - labeled, axis=-1))),
    }


def _scores(preds: dict[str, np.ndarray], gt: np.ndarray, train: np.ndarray) -> dict[str, Any]:
    """Median and mean JPE of answers and references against ``gt``, with comparisons."""
    from freipose.nn.compare import paired_difference
    from freipose.nn.evaluate import jpe
    from freipose.nn.references import reference_predictions

    preds = {**preds, **reference_predictions(train, gt)}
    errs = {n: jpe(p, gt) for n, p in preds.items()}
    comps = [paired_difference(errs[n], errs[b], n, b)
             for n, b in (("voxel_P1", "baseline"), ("voxel_P1", AT_HELD_OUT))]  # fmt: skip
    return {
        "median": {n: float(np.nanmedian(e)) for n, e in errs.items()},
        "mean": {n: float(np.mean(e[np.isfinite(e)])) for n, e in errs.items()},
        "n": int(np.isfinite(errs["voxel_P1"]).sum()),
        "per_keypoint": {n: np.nanmedian(errs[n], axis=0).tolist() for n in NETWORKS},
        "comparisons": [c.to_dict() for c in comps if c is not None],
    }


def against_labels(run: Path) -> dict[str, Any]:
    """What ``freipose eval`` wrote: medians, means, references and comparisons."""
    m = json.loads((run / "eval" / "metrics.json").read_text(encoding="utf-8"))
    med = {n: m[n]["overall"]["median"] for n in NETWORKS}
    med.update({n: r["median_mm"] for n, r in m.get("references", {}).items()})
    want = {("voxel_P1", "baseline"), ("voxel_P1", AT_HELD_OUT)}
    comps = [c for c in m.get("comparisons", []) if (c["a"], c["b"]) in want]
    mean = {c["a"]: c["mean_a"] for c in comps} | {c["b"]: c["mean_b"] for c in comps}
    return {"median": med, "mean": mean, "comparisons": comps, "n": m["voxel_P1"]["overall"]["n"]}


def _comparison(c: dict[str, Any], stat: str) -> str:
    """``difference [low, high] verdict`` of the medians (``""``) or the means (``"mean_"``)."""
    d, lo, hi = (c[f"{stat}difference"], c[f"{stat}low"], c[f"{stat}high"])
    return f"{d:+.2f} [{lo:+.2f}, {hi:+.2f}] {c[stat + 'verdict']}"


SIDES = (("labels", "held-out labels"), ("truth", "truth, labeled kp"),
         ("truth_all", "truth, every kp"))  # fmt: skip


def print_table(say: Callable[[str], None], seed: int, scores: dict[str, dict]) -> None:
    """One seed's table: median and mean JPE against the labels and the truth, comparisons."""
    sides = [(k, t) for k, t in SIDES if k in scores]
    n = ", ".join(f"{scores[k]['n']} vs {t}" for k, t in sides)
    say(f"\nseed {seed}: JPE mm, median / mean (keypoints: {n})")
    say(f"  {'':32s}" + "".join(f" {t:>19s}" for _, t in sides))
    for name in (*NETWORKS, AT_HELD_OUT, AT_TRAINING):
        cells = []
        for k, _ in sides:
            med, mean = scores[k]["median"].get(name), scores[k]["mean"].get(name)
            m = f"{mean:.2f}" if mean is not None else "-"
            cells.append(f" {(f'{med:.2f}' if med is not None else '-') + ' / ' + m:>19s}")
        say(f"  {name:32s}" + "".join(cells))
    say("  median per keypoint vs the truth, every kp (labeled share of the held-out instants):")
    every = scores["truth_all"]["per_keypoint"]
    for j, kp in enumerate(scores["keypoints"]):
        say(
            f"    {kp:24s} voxel_P1 {every['voxel_P1'][j]:6.2f}  baseline "
            f"{every['baseline'][j]:6.2f}  ({scores['labeled_share'][j]:.0%} labeled)"
        )
    say("  paired differences, mm [95 % block-bootstrap interval]:")
    for i, c in enumerate(scores["labels"]["comparisons"]):
        say(f"    {c['a']} - {c['b']}:")
        for k, t in sides:
            ck = scores[k]["comparisons"][i]
            say(f"      vs {t:18s} median {_comparison(ck, '')}; mean {_comparison(ck, 'mean_')}")


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="work and result folder")
    ap.add_argument("--frames", type=int, default=600, help="frames of the recording")
    ap.add_argument("--size", default="320x256", help="image size WxH")
    ap.add_argument("--data-seed", type=int, default=0, help="the generator's seed")
    ap.add_argument("--steps", type=int, default=600, help="training steps of each network")
    ap.add_argument("--preset", default="small", help="network preset")
    ap.add_argument("--init", default="base", help="base, scratch or a checkpoint")
    ap.add_argument("--blocks", type=int, default=3, help="held-out time blocks")
    ap.add_argument("--gap", type=int, default=30, help="frames between held-out and training")
    ap.add_argument("--seeds", type=int, default=1, help="training seeds (0, 1, ...)")
    ap.add_argument("--first-seed", type=int, default=0, help="the first training seed")
    ap.add_argument("--schedule", action="append", default=[], metavar="KEY=VALUE",
                    help="a [schedule] setting of both trainings (TOML), repeatable")  # fmt: skip
    return ap


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; print the tables and write ``results.json``."""
    a = _parser().parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    say = print
    timings_path = a.out / "timings.json"
    times = json.loads(timings_path.read_text()) if timings_path.exists() else {}
    prepare(a.out, a, times.setdefault("data", {}))
    align = truth_alignment(a.out)
    say(f"rig: a mouse, 4 fisheye grayscale cameras at {a.size} px, reflections, bedding, "
        f"resting 60 %; {a.frames} frames at 30 fps; held out: {a.blocks} time blocks "
        f"(a quarter of the instants, gap {a.gap} frames); {a.steps} steps each "
        f"({a.preset} preset, init {a.init})")  # fmt: skip
    say(f"imported labels vs the truth: median {align[3]:.2f} mm (the label tool's error); "
        f"calibration scale vs truth {align[0]:.5f}")  # fmt: skip
    results: dict[str, Any] = {"config": {k: str(v) for k, v in vars(a).items()}, "seeds": {}}
    seeds = range(a.first_seed, a.first_seed + a.seeds)
    for seed in seeds:
        run = a.out / f"seed{seed}"
        times.setdefault(f"seed{seed}", {}).update(train_and_eval(a.out, run, a, seed))
        timings_path.write_text(json.dumps(times, indent=2))
        scores = {"labels": against_labels(run), **against_truth(a.out, run, align)}
        print_table(say, seed, scores)
        results["seeds"][str(seed)] = {**scores, "seconds": times[f"seed{seed}"]}
    data_s = sum(v for k, v in times["data"].items() if k != "synth" and k != "calib")
    for seed in seeds:
        t = times[f"seed{seed}"]
        total = data_s + sum(t.values())
        parts = ", ".join(f"{k} {v:.0f} s" for k, v in {**times["data"], **t}.items())
        say(f"seed {seed}: import + split + training + eval {total:.0f} s ({parts})")
        sc = results["seeds"][str(seed)]
        figures = {f"{stat} JPE mm vs {k}": sc[k][stat] for k, _ in SIDES if k in sc
                   for stat in ("median", "mean")}  # fmt: skip
        figures["labels vs truth median mm"] = float(align[3])
        figures["seconds"] = {"total": total, **t}
        settings = {k: str(v) for k, v in vars(a).items() if k not in ("out", "seeds")}
        write_result("own_rig", figures, extra={"seed": seed, **settings})
    results["timings"] = times
    (a.out / "results.json").write_text(json.dumps(results, indent=2))
    say(f"wrote {a.out / 'results.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
