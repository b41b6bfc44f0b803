r"""The ``study`` preset analysed on predicted poses: rendered, predicted, analysed.

``freipose analyze simulate --preset study`` writes the study's poses with a model of a
pose network's error; this benchmark measures the real chain instead. It renders every
recording of the synthetic ``study`` preset (``freipose.synth.study``: 3 animals x 8 days
of 30 s, 4 train and 4 test days, the demo's stimulation with each recording's own
schedule and ``events.csv``) as videos with the rig, image size and scene settings of the
demo (``freipose.demo.steps.synth.session_scene``), each animal its own body (animal 1 is
the demo's rat, whose labeled day the network was fine-tuned on; that day is not in the
study) and each day its own seed; predicts them with a finished demo's fine-tuned network
and detector in its calibrated frame (``freipose predict``, the local executor: one
recording per one-thread worker); optionally smooths them (``freipose smooth``); and runs
``freipose analyze`` with the tutorial's settings.

The design comes from the power estimate: ``freipose analyze design`` on the pilot (the
demo's own analysed study: one animal, a train and a test day, predicted poses) with the
tutorial's variable, trials in whole recordings (7 trials each, half train, half test).
The study is analysed twice: with the recommended design (the first days of every animal,
as many as the recommended trials need) and with the whole preset.

It records (``benchmarks/_results.py``): the median joint position error of every
recording against the rendered truth (and the share of frames with a pose), the design's
power table and recommended trials, and per analysed design and animal the best variable,
the stimulated paw's best variable (rank, F1, p-value, significance), the significant
variables of other body parts, and whether the paw is found (significant in every animal)
and correctly attributed (the best variable and every significant one on the paw).

A rendered or predicted recording is kept when the script runs again. Scale options
(``--animals``, ``--days``, ``--frames``, ``--cameras``, ``--size``, ``--stim``) make a
small version; without ``--demo`` the shipped ``small`` base network predicts with
background subtraction in the rendered rig's true calibration.

Usage::

    python benchmarks/study_predicted.py --demo /work/runs/demo-seed0 --work study_bench
    python benchmarks/study_predicted.py --animals 1 --days 2 --frames 50 --cameras 2 \
        --size 160x128 --stim duration_s=0.4 --stim spacing_s=0.4 --stim onset_s=0.2 \
        --onset-delay 0 --margin 0.1 --stft-window 8 --pilot pilot/study.toml
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from _results import write_result

STIM_PART = "Paw Front Right"
DESIGN_VARIABLE = "floor_dist_stft_4.69Hz[Paw Front Right]"  # the tutorial's


@dataclass(frozen=True)
class Source:
    """Where the network, detector and calibrated frame come from.

    Attributes:
        model: pose checkpoint.
        detector: detector checkpoint (None: background subtraction).
        calibration: the rig's calibration (None: each session's true calibration).
        alignment: ``scale``, ``R``, ``t`` mapping the calibrated to the true world frame
            (None: the calibration is the true one).
        pilot: the pilot study of the power estimate (None: give ``--pilot``).
        demo_preset: the demo preset whose rig and scene the recordings use.
    """

    model: Path
    detector: Path | None
    calibration: Path | None
    alignment: dict[str, Any] | None
    pilot: Path | None
    demo_preset: Any


def load_source(demo: Path | None) -> Source:
    """The finished demo ``demo``'s network, detector and calibration, or the shipped base."""
    from importlib.resources import files

    from freipose.demo.markers import step_results
    from freipose.demo.presets import PRESETS

    if demo is None:
        return Source(Path(str(files("freipose.models") / "voxel_small.pt")), None, None, None,
                      None, PRESETS["small"])  # fmt: skip
    trained = step_results(demo, "train")
    preset = json.loads((demo / "summary.json").read_text())["preset"]
    return Source(
        model=Path(trained["pose"]["checkpoint"]),
        detector=Path(trained["detector"]["checkpoint"]),
        calibration=demo / "calibration" / "calibration.toml",
        alignment=step_results(demo, "calibrate")["alignment"],
        pilot=demo / "analysis" / "study.toml",
        demo_preset=PRESETS[preset],
    )


def study_preset(args: argparse.Namespace) -> Any:
    """The ``study`` preset with the scale options applied."""
    from freipose.synth.study import STUDY_PRESETS

    preset = STUDY_PRESETS["study"]
    stim = dict(preset.stimulation)
    for item in args.stim:
        key, _, value = item.partition("=")
        stim[key] = type(stim[key])(value) if key in stim else float(value)
    days = args.days or preset.days
    changes = dict(animals=args.animals or preset.animals, days=days,
                   train_days=args.train_days or max(1, days // 2),
                   frames=args.frames or preset.frames, stimulation=stim)  # fmt: skip
    return dataclasses.replace(preset, **changes)


def recording_names(preset: Any) -> list[tuple[int, int, str]]:
    """(animal index, day index, name) of every recording, animal by animal."""
    return [(a, d, f"rat{a + 1}_day{d + 1}") for a in range(preset.animals)
            for d in range(preset.days)]  # fmt: skip


def day_seed(animal: int, day: int) -> int:
    """The seed of a recording (its motion, schedule, lighting, noise; none is a demo day's)."""
    return 1000 + 100 * animal + day


def animal_seed(animal: int, demo_seed: int) -> int:
    """The body of animal ``animal``: the first is the demo's rat, the others new ones."""
    return demo_seed if animal == 0 else 100 + animal


def render(work: Path, preset: Any, args: argparse.Namespace, source: Source) -> list[Path]:
    """Render every recording of the study (kept when already rendered)."""
    from freipose.demo.steps.synth import session_scene
    from freipose.synth import generate_session
    from freipose.synth.study import recording_stimulation

    demo = dataclasses.replace(source.demo_preset, session_frames=preset.frames,
                               fps=preset.fps)  # fmt: skip
    if args.cameras:
        demo = dataclasses.replace(demo, n_cameras=args.cameras)
    if args.size:
        demo = dataclasses.replace(demo, size=tuple(int(v) for v in args.size.split("x")))
    folders = []
    names = recording_names(preset)
    for i, (a, d, name) in enumerate(names):
        folder = work / "recordings" / name
        folders.append(folder)
        videos = list(folder.glob("cam*.mp4"))
        if (folder / "labels.h5").is_file() and len(videos) == demo.n_cameras:
            say(f"[render {i + 1}/{len(names)}] {name}: rendered, kept")
            continue
        seed = day_seed(a, d)
        stim = recording_stimulation(preset, np.random.default_rng(seed))
        cfg = dataclasses.replace(session_scene(demo, seed), stimulation=stim,
                                  animal_seed=animal_seed(a, demo.sessions[0].seed))  # fmt: skip
        t0 = time.perf_counter()
        generate_session(folder, cfg, progress=False)
        say(f"[render {i + 1}/{len(names)}] {name}: {demo.n_cameras} cameras x {preset.frames} "
            f"frames in {time.perf_counter() - t0:.0f} s")  # fmt: skip
    return folders


def predict(folders: list[Path], out: Path, source: Source, args: argparse.Namespace) -> float:
    """Predict the recordings not yet predicted into ``out``; returns the seconds it took."""
    todo = [f for f in folders if not (out / f"{f.name}.poses.h5").is_file()]
    say(f"[predict] {len(folders) - len(todo)} of {len(folders)} recordings predicted, kept; "
        f"predicting {len(todo)}")  # fmt: skip
    if not todo:
        return 0.0
    cmd = [sys.executable, "-m", "freipose.cli.main", "predict", *map(str, todo),
           "--model", str(source.model), "--device", "cpu", "-o", str(out)]  # fmt: skip
    if source.detector is not None:
        cmd += ["--detector", str(source.detector)]
    else:
        cmd += ["--method", "bgsub"]
    if source.calibration is not None:
        cmd += ["--calibration", str(source.calibration)]
    else:  # each rendered session's own true calibration
        for f in todo:
            (f / "calibration.toml").write_bytes((f / "true_calibration.toml").read_bytes())
    if args.executor == "local":
        frames = args.frames or 750
        cfg = out.parent / "local_executor.toml"
        cfg.write_text(f'[cluster]\nexecutor = "local"\ncpus = 1\narray_parallelism = '
                       f"{args.cores}\nchunk_frames = {frames}\npoll_s = 1.0\n")  # fmt: skip
        cmd += ["--cluster", str(cfg)]
    else:
        cmd += ["--threads", str(args.cores)]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True)
    return time.perf_counter() - t0


def smooth(poses: Path, out: Path) -> None:
    """Smooth the predicted poses not yet smoothed into ``out`` (``freipose smooth``)."""
    todo = [p for p in sorted(poses.glob("*.poses.h5")) if not (out / p.name).is_file()]
    say(f"[smooth] {len(todo)} recordings")
    if todo:
        subprocess.run([sys.executable, "-m", "freipose.cli.main", "smooth", *map(str, todo),
                        "-o", str(out)], check=True)  # fmt: skip


def recording_errors(folder: Path, poses: Path, alignment: dict[str, Any] | None) -> dict:
    """Median joint position error (mm) against the rendered truth, and the share found."""
    from freipose.demo.context import truth_to_calibrated
    from freipose.io.labels import read_labels_h5
    from freipose.io.poses import read_poses_h5

    data = read_poses_h5(poses)
    lab = read_labels_h5(folder / "labels.h5")
    gt = lab.points3d if alignment is None else truth_to_calibrated(lab.points3d, alignment)
    rows = {int(f): i for i, f in enumerate(lab.frame_index)}
    order = [lab.keypoints.index(k) for k in data.keypoints]
    gt = gt[np.array([rows[int(f)] for f in data.frame_index])][:, order]
    err = np.linalg.norm(data.poses - gt, axis=-1)
    found = np.isfinite(data.poses).all(-1).any(-1)
    paw = data.keypoints.index(STIM_PART)
    return {"jpe_median_mm": float(np.nanmedian(err)), "jpe_mean_mm": float(np.nanmean(err)),
            "paw_jpe_median_mm": float(np.nanmedian(err[:, paw])),
            "found_share": float(found.mean())}  # fmt: skip


def write_study_toml(path: Path, poses: Path, folders: list[Path], preset: Any, days: int) -> Path:
    """The manifest of the first ``days`` days of every animal (the first half train)."""
    from freipose.analysis.study import recording_entry

    train = max(1, days // 2)
    entries = []
    for a, d, name in recording_names(preset):
        if d >= days:
            continue
        folder = next(f for f in folders if f.name == name)
        rel = os.path.relpath(poses / f"{name}.poses.h5", path.parent)
        ev = os.path.relpath(folder / "events.csv", path.parent)
        entries.append(recording_entry(name, Path(rel).as_posix(), Path(ev).as_posix(),
                                       f"rat{a + 1}", "paw_stimulation",
                                       "train" if d < train else "test"))  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    text = (f"# benchmarks/study_predicted.py: {preset.animals} animals x {days} days\n"
            'skeleton = "rat"\n\n' + "\n".join(entries))  # fmt: skip
    path.write_text(text, encoding="utf-8")
    return path


def analysis_settings(args: argparse.Namespace) -> list[str]:
    """The options of ``freipose analyze`` and ``analyze design`` (the tutorial's)."""
    return ["--stft-window", str(args.stft_window), "--onset-delay", str(args.onset_delay),
            "--margin", str(args.margin)]  # fmt: skip


def analyze(study: Path, out: Path, args: argparse.Namespace) -> Path:
    """``freipose analyze`` of ``study`` into ``out`` (kept when already analysed)."""
    if not (out / "attribution.csv").is_file():
        subprocess.run([sys.executable, "-m", "freipose.cli.main", "analyze", str(study),
                        "-o", str(out), "--no-figures", "--overwrite",
                        *analysis_settings(args)], check=True)  # fmt: skip
    return out / "attribution.csv"


def paw_findings(attribution: Any) -> dict[str, Any]:
    """Per animal: the best variable, the paw's best one, the significant ones elsewhere.

    Args:
        attribution: ``attribution.csv`` as a DataFrame (columns animal, variable, part, f1,
            p_adjusted, significant).

    Returns:
        ``animals`` (per animal: ``best_variable``, ``best_part``, ``paw_rank`` (1 = best
        F1), ``paw_variable``, ``paw_f1``, ``paw_p_adjusted``, ``paw_significant``
        (variables of the paw that are significant), ``significant_other`` (names of the
        significant variables of other parts)); ``paw_significant_in_every_animal``;
        ``correctly_attributed`` (in every animal the best variable is the paw's and no
        variable of another part is significant).
    """
    animals = {}
    for animal, rows in attribution.groupby("animal", sort=True):
        rows = rows.sort_values("f1", ascending=False, kind="stable").reset_index(drop=True)
        paw = rows.index[rows["part"] == STIM_PART]
        sig = rows["significant"].astype(bool)
        first = int(paw[0]) if len(paw) else None
        animals[str(animal)] = {
            "best_variable": str(rows["variable"].iloc[0]),
            "best_part": str(rows["part"].iloc[0]),
            "best_f1": float(rows["f1"].iloc[0]),
            "paw_rank": None if first is None else first + 1,
            "paw_variable": None if first is None else str(rows["variable"].iloc[first]),
            "paw_f1": None if first is None else float(rows["f1"].iloc[first]),
            "paw_p_adjusted": None if first is None else float(rows["p_adjusted"].iloc[first]),
            "paw_significant": int((sig & (rows["part"] == STIM_PART)).sum()),
            "significant_other": rows.loc[sig & (rows["part"] != STIM_PART), "variable"].tolist(),
        }
    found = bool(animals) and all(v["paw_significant"] > 0 for v in animals.values())
    right = found and all(v["best_part"] == STIM_PART and not v["significant_other"]
                          for v in animals.values())  # fmt: skip
    return {"animals": animals, "paw_significant_in_every_animal": found,
            "correctly_attributed": right}  # fmt: skip


def design(pilot: Path, out: Path, args: argparse.Namespace, animals: int) -> dict[str, Any]:
    """``freipose analyze design`` on the pilot: the power table and the recommended trials."""
    import pandas as pd

    from freipose.analysis.design import recommended

    counts = ",".join(map(str, sorted({1, animals})))
    if not (out / "design.csv").is_file():
        subprocess.run([sys.executable, "-m", "freipose.cli.main", "analyze", "design",
                        str(pilot), "-o", str(out), "--variable", args.design_variable,
                        "--trials", args.design_trials, "--animals", counts,
                        "--simulations", str(args.simulations), *analysis_settings(args)],
                       check=True)  # fmt: skip
    table = pd.read_csv(out / "design.csv")
    rec = recommended(table, args.power)
    return {"pilot": str(pilot), "variable": args.design_variable, "power_wanted": args.power,
            "simulations": args.simulations,
            "table": json.loads(table.to_json(orient="records")),
            "recommended_trials_per_animal": {str(k): v for k, v in rec.items()}}  # fmt: skip


def design_days(trials: int | None, per_recording: int, days: int) -> int:
    """Recordings per animal for ``trials`` trials: whole recordings, an even number, <= days.

    None (no tried number reaches the power) or more than the preset holds: all ``days``.
    """
    if trials is None:
        return days
    need = math.ceil(trials / per_recording)
    return min(days, need + need % 2)


def say(msg: str) -> None:
    """A progress line (flushed: the log of a background run shows it at once)."""
    print(msg, flush=True)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--demo", type=Path, help="finished `freipose demo` folder (its network, "
                    "detector, calibration and analysed study as the pilot)")  # fmt: skip
    ap.add_argument("--work", type=Path, default=Path("study_predicted_bench"))
    ap.add_argument("--pilot", type=Path, help="pilot study.toml [default: the demo's]")
    ap.add_argument("--animals", type=int, help="animals [default: the preset's, 3]")
    ap.add_argument("--days", type=int, help="recordings per animal [default: 8]")
    ap.add_argument("--train-days", type=int, help="train recordings [default: half]")
    ap.add_argument("--frames", type=int, help="frames per recording [default: 750]")
    ap.add_argument("--cameras", type=int, help="cameras [default: the demo's, 7]")
    ap.add_argument("--size", help="image size WxH [default: the demo's, 320x256]")
    ap.add_argument("--stim", action="append", default=[], metavar="KEY=VALUE",
                    help="override a field of the preset's stimulation")  # fmt: skip
    ap.add_argument("--executor", choices=("local", "none"), default="local")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--smooth", action="store_true", help="also analyse smoothed poses")
    ap.add_argument("--stft-window", type=int, default=32)
    ap.add_argument("--onset-delay", type=float, default=0.6)
    ap.add_argument("--margin", type=float, default=0.5)
    ap.add_argument("--design-variable", default=DESIGN_VARIABLE)
    ap.add_argument("--design-trials", default="14,28,42,56,70")
    ap.add_argument("--simulations", type=int, default=100)
    ap.add_argument("--power", type=float, default=0.8)
    return ap.parse_args(argv)


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Render, predict, (smooth,) design and analyse; returns the figures."""
    import pandas as pd

    t_start = time.perf_counter()
    source = load_source(args.demo)
    pilot = args.pilot or source.pilot
    if pilot is None:
        raise SystemExit("no pilot study: pass --demo DIR or --pilot STUDY.toml")
    preset = study_preset(args)
    work = args.work
    t0 = time.perf_counter()
    folders = render(work, preset, args, source)
    render_s = time.perf_counter() - t0
    predict_s = predict(folders, work / "poses", source, args)
    sets = {"predicted": work / "poses"}
    if args.smooth:
        smooth(work / "poses", work / "smoothed")
        sets["smoothed"] = work / "smoothed"
    errors = {f.name: recording_errors(f, sets["predicted"] / f"{f.name}.poses.h5",
                                       source.alignment) for f in folders}  # fmt: skip
    jpe = [e["jpe_median_mm"] for e in errors.values()]
    say(f"[truth] median JPE per recording {min(jpe):.2f}-{max(jpe):.2f} mm "
        f"(median {np.median(jpe):.2f})")  # fmt: skip
    plan = design(pilot, work / "design", args, preset.animals)
    per_rec = preset.trials_per_recording
    rec_trials = plan["recommended_trials_per_animal"].get(str(preset.animals))
    days_rec = design_days(rec_trials, per_rec, preset.days)
    say(f"[design] recommended trials per animal ({preset.animals} animals): {rec_trials}; "
        f"{days_rec} recordings of {per_rec} trials")  # fmt: skip
    designs = {"recommended": days_rec, "preset": preset.days}
    analyses: dict[str, Any] = {}
    for kind, poses in sets.items():
        for dname, days in designs.items():
            if dname == "preset" and days == days_rec and "recommended" in designs:
                analyses[f"{kind}_{dname}"] = {"same_as": f"{kind}_recommended"}
                continue
            tag = f"{kind}_{days}days"
            study = write_study_toml(work / "studies" / f"{tag}.toml", poses, folders, preset, days)
            att = pd.read_csv(analyze(study, work / "results" / tag, args))
            found = paw_findings(att)
            found.update(days_per_animal=days, trials_per_animal=days * per_rec)
            analyses[f"{kind}_{dname}"] = found
            for animal, v in found["animals"].items():
                say(f"[{kind}, {days} days] {animal}: best {v['best_variable']} (F1 "
                    f"{v['best_f1']:.2f}); paw rank {v['paw_rank']} {v['paw_variable']} "
                    f"F1 {v['paw_f1']:.2f} p_adj {v['paw_p_adjusted']:.2g}; significant: "
                    f"{v['paw_significant']} on the paw, {len(v['significant_other'])} "
                    "elsewhere")  # fmt: skip
            say(f"[{kind}, {days} days] paw significant in every animal: "
                f"{found['paw_significant_in_every_animal']}; correctly attributed: "
                f"{found['correctly_attributed']}")  # fmt: skip
    return {
        "recordings": len(folders), "frames_per_recording": preset.frames,
        "trials_per_recording": per_rec, "animals": preset.animals, "days": preset.days,
        "errors": errors, "jpe_median_mm_median": float(np.median(jpe)),
        "jpe_median_mm_range": [float(min(jpe)), float(max(jpe))],
        "design": plan, "analyses": analyses,
        "render_s": render_s, "predict_s": predict_s,
        "total_s": time.perf_counter() - t_start,
    }  # fmt: skip


def main(argv: list[str] | None = None) -> Path | None:
    args = parse_args(argv)
    figures = run(args)
    print(json.dumps({k: v for k, v in figures.items() if k != "errors"}, indent=1))
    extra = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()
             if k != "work"}  # fmt: skip
    return write_result("study_predicted", figures, extra=extra)


if __name__ == "__main__":
    main()
