"""Benchmark: the demo's stimulation classifier trained on its labeled day or on other days.

The demo labels frames of one recording (``rat1_day1``), trains the pose network on them,
and trains the full classifier on another day (``rat1_day3``) and scores it on the held-out
day (``rat1_day2``). This script predicts the labeled day too, renders more recordings of
the demo's rat (the preset's scene with other seeds) and predicts them with the demo's
trained detector and voxel network, and prints the full classifier's balanced accuracy on
the held-out day when it is trained on the labeled day, on each day without labels (the
demo's training day first), and on all of those; with the classifier's score on its own
train frames and the best single variable's score.

    python benchmarks/classifier_days.py DEMO [--seeds 4] [--out DEMO/classifier_days]

``DEMO`` is a finished ``freipose demo`` folder of the ``small`` preset. Rendering and
predicting a recording take about 1.5 minutes on 2 cores; finished ones are kept.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass
from pathlib import Path

from _results import write_result


@dataclass(frozen=True)
class Recording:
    """A recording of the study: its poses, its events and its split."""

    name: str
    poses: Path
    events: Path


@dataclass(frozen=True)
class Score:
    """The full classifier trained on ``train``, scored on the held-out day."""

    train: tuple[str, ...]
    balanced_accuracy: float
    train_balanced_accuracy: float
    best_variable: str
    best_variable_accuracy: float


def study_text(train: list[Recording], test: Recording) -> str:
    """A study manifest of one rat and one condition: ``train`` recordings and ``test``."""
    from freipose.analysis.study import recording_entry

    entries = []
    for r, split in [(r, "train") for r in train] + [(test, "test")]:
        poses, events = r.poses.resolve().as_posix(), r.events.resolve().as_posix()
        entries.append(recording_entry(r.name, poses, events, "rat1", "stimulation", split))
    return 'skeleton = "rat"\n\n' + "\n".join(entries)


def score(folder: Path, train: list[Recording], test: Recording, acfg, vcfg) -> Score:
    """Run ``freipose analyze`` on one study in ``folder`` and read the full classifier."""
    from freipose.analysis.report import analyze_study

    folder.mkdir(parents=True, exist_ok=True)
    (folder / "study.toml").write_text(study_text(train, test), encoding="utf-8")
    res = analyze_study(
        folder / "study.toml", folder / "results", None, "world", vcfg, acfg,
        make_figures=False, say=lambda m: None,
    )  # fmt: skip
    row = res.classification.iloc[0]
    best = res.attribution.loc[res.attribution["balanced_accuracy"].idxmax()]
    return Score(
        tuple(r.name for r in train),
        float(row["balanced_accuracy"]),
        float(row["train_balanced_accuracy"]),
        str(best["variable"]),
        float(best["balanced_accuracy"]),
    )


def train_sets(labeled: Recording, others: list[Recording]) -> list[list[Recording]]:
    """The labeled day alone, each other day alone, and all other days together."""
    sets = [[labeled]] + [[r] for r in others]
    return sets + [list(others)] if len(others) > 1 else sets


def predict_day(demo: Path, folder: Path, out: Path) -> Path:
    """Predict the recording in ``folder`` with the demo's networks (kept when finished)."""
    from freipose.demo.markers import step_results
    from freipose.io.session import discover_sessions
    from freipose.predict.network import DetectorSpec, predict_sessions

    trained = step_results(demo, "train")
    spec = DetectorSpec("detector", Path(trained["detector"]["checkpoint"]), None, 40, 2)
    sessions = discover_sessions([folder], demo / "calibration" / "calibration.toml")
    (res,) = predict_sessions(
        sessions, Path(trained["pose"]["checkpoint"]), spec, out / "poses", progress=False
    )
    return res.path


def unlabeled_days(demo: Path, seeds: list[int], out: Path, preset: str) -> list[Recording]:
    """Render and predict one recording of the demo's rat per seed (kept when finished)."""
    from freipose.demo.presets import PRESETS
    from freipose.demo.steps.synth import session_scene
    from freipose.synth import generate_session

    recs = []
    for seed in seeds:
        name = f"rat1_seed{seed}"
        folder = out / "recordings" / name
        if not (folder / "events.csv").is_file():
            generate_session(folder, session_scene(PRESETS[preset], seed), progress=False)
        recs.append(Recording(name, predict_day(demo, folder, out), folder / "events.csv"))
    return recs


def demo_recording(demo: Path, name: str) -> Recording:
    """A recording of the demo itself, with its predicted poses."""
    return Recording(
        name, demo / "poses" / f"{name}.poses.h5", demo / "recordings" / name / "events.csv"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("demo", type=Path, help="a finished `freipose demo` folder")
    ap.add_argument(
        "--seeds",
        type=int,
        nargs="+",
        default=[4],
        help="seeds of the extra days (the demo's own days are 1, 2 and 3)",
    )
    ap.add_argument("--out", type=Path, default=None, help="default: DEMO/classifier_days")
    ap.add_argument("--preset", default="small")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    import torch

    from freipose.analysis.config import AttributionConfig
    from freipose.analysis.variables import VariableConfig
    from freipose.demo.presets import PRESETS

    torch.set_num_threads(args.threads)
    p = PRESETS[args.preset]
    out = args.out or args.demo / "classifier_days"
    label_name = p.with_split("label")[0].name
    train_name = p.with_split("train")[0].name
    test_name = p.with_split("test")[0].name
    folder = args.demo / "recordings" / label_name
    labeled = Recording(label_name, predict_day(args.demo, folder, out), folder / "events.csv")
    others = [demo_recording(args.demo, train_name)]
    others += unlabeled_days(args.demo, args.seeds, out, args.preset)
    test = demo_recording(args.demo, test_name)
    acfg, vcfg = AttributionConfig(**p.analysis), VariableConfig(stft_window=p.stft_window)
    print(f"full classifier scored on {test_name} (predicted poses of {args.demo}):")
    print("trained on                      | balanced acc. | on its train frames | best single")
    figures = {}
    for train in train_sets(labeled, others):
        s = score(out / "studies" / "+".join(r.name for r in train), train, test, acfg, vcfg)
        label = " + ".join(s.train) + (" (labeled)" if s.train == (label_name,) else "")
        print(f"{label:31s} | {s.balanced_accuracy:13.3f} | {s.train_balanced_accuracy:19.3f} "
              f"| {s.best_variable_accuracy:.3f} {s.best_variable}")  # fmt: skip
        figures[" + ".join(s.train)] = {
            "balanced_accuracy": s.balanced_accuracy,
            "train_balanced_accuracy": s.train_balanced_accuracy,
            "best_variable_accuracy": s.best_variable_accuracy,
            "best_variable": s.best_variable,
        }
    extra = {"demo": str(args.demo), "seeds": args.seeds, "preset": args.preset, "test": test_name}
    write_result("classifier_days", figures, extra=extra)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
