"""Per-animal poses among several animals: a network trained on social scenes vs on one animal.

The voxel network sees, in each animal's cube, whatever else is there: with several animals,
parts of the others (in contact, climbing over, hiding a paw). This benchmark asks what that
costs, at the same training budget:

* data (``freipose synth``, 4 cameras, ``--size``, 10 fps): ``--train`` training sessions
  (seeds 2000 + i) and ``--test`` held-out sessions (seeds 3000 + i) of ``--frames``
  frames, once with one animal and once with two animals of different coats; labels are
  the generator's exact ones (a social session has a row per animal and frame);
* networks, from the shipped base model at the same ``--steps`` and batch: ``single``,
  trained on the single-animal sessions, and ``social``, trained on the social sessions;
* scores (``freipose eval``, the cube centred on each animal's labeled centre, so that
  the network is scored and not the tracking): median P1 JPE of ``single`` on the
  single-animal held-out sessions (the single-animal case), of ``social`` on each animal
  of the social held-out sessions, and, as a reference, of ``single`` on the social ones
  (a single-animal network among several animals). The issue's target: each animal's
  error with the social network within 1.3x of the single-animal case.

``--seeds N`` repeats the trainings with N seeds (the data stay); a finished step is
skipped when run again on the same ``--out``.

Example (about 25 minutes on 2 cores)::

    python benchmarks/social_poses.py --out bench/social_poses --seeds 2
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from _results import write_result

SCENE = ["--cameras", "4", "--fps", "10", "--coat-mix", "different"]


def freipose(args: list[str]) -> float:
    """Run ``freipose ARGS`` in this process; returns its wall time in seconds.

    Raises:
        SystemExit: the command failed.
    """
    from freipose.cli.main import cli

    t0 = time.perf_counter()
    try:
        cli.main(["-q", *args], standalone_mode=False)
    except Exception as exc:  # a benchmark stops at the first failing command
        raise SystemExit(f"freipose {' '.join(args)} failed: {exc}") from exc
    return time.perf_counter() - t0


def step(done: Path, args: list[str]) -> None:
    """Run a command unless its output ``done`` exists."""
    if not done.exists():
        freipose(args)


def sessions(out: Path, a: argparse.Namespace) -> dict[str, Path]:
    """Render the sessions and merge their labels: ``{animals}_{train|test}`` -> labels file."""
    files = {}
    for animals in (1, 2):
        for part, first, n in (("train", 2000, a.train), ("test", 3000, a.test)):
            names = []
            for i in range(n):
                rec = out / "data" / f"a{animals}_{part}{i}"
                args = ["synth", str(rec), *SCENE, "--animals", str(animals), "--size", a.size,
                        "--frames", str(a.frames), "--seed", str(first + i)]  # fmt: skip
                step(rec / "labels.h5", args)
                names.append(str(rec / "labels.h5"))
            merged = out / "labels" / f"a{animals}_{part}.h5"
            merged.parent.mkdir(parents=True, exist_ok=True)
            step(merged, ["labels", "merge", *names, "-o", str(merged)])
            files[f"{animals}_{part}"] = merged
    for animal in ("animal0", "animal1"):  # the social held-out labels, one animal each
        one = out / "labels" / f"a2_test_{animal}.h5"
        if not one.exists():
            _one_animal(files["2_test"], animal, one)
        files[f"2_test_{animal}"] = one
    return files


def _one_animal(path: Path, animal: str, out: Path) -> None:
    """The rows of one animal of a multi-animal labels file."""
    from freipose.io.labels import read_labels_h5, write_labels_h5

    labels = read_labels_h5(path)
    if labels.individual is None:
        raise SystemExit(f"{path} has no individuals")
    keep = np.flatnonzero(np.asarray(labels.individual) == animal)
    sub = labels.select(keep)
    tmp = out.with_suffix(".tmp.h5")
    write_labels_h5(sub, tmp)
    tmp.replace(out)


def train(out: Path, labels: Path, a: argparse.Namespace, seed: int) -> Path:
    """Fine-tune the base model on ``labels``; returns the checkpoint."""
    out.mkdir(parents=True, exist_ok=True)
    cfg = out / "train.toml"
    cfg.write_text(
        f'[data]\nlabels = "{labels}"\nskeleton = "rat"\n\n[model]\npreset = "{a.preset}"\n\n'
        f"[schedule]\nsteps = {a.steps}\ncheckpoint_every = {a.steps}\nseed = {seed}\n",
        encoding="utf-8",
    )
    model = out / "pose" / "model.pt"
    step(model, ["train", str(cfg), "--out", str(out / "pose"), "--init", a.init])
    return model


def evaluate(model: Path, labels: Path, out: Path) -> dict[str, float]:
    """P1 and P0 median and mean JPE of ``model`` on ``labels`` (``freipose eval``)."""
    step(out / "metrics.json", ["eval", str(model), str(labels), "-o", str(out)])
    m = json.loads((out / "metrics.json").read_text(encoding="utf-8"))
    return {
        "P1_median": m["voxel_P1"]["overall"]["median"],
        "P0_median": m["voxel_P0"]["overall"]["median"],
        "n": m["voxel_P1"]["overall"]["n"],
    }


def run_seed(out: Path, files: dict[str, Path], a: argparse.Namespace, seed: int) -> dict:
    """Train both networks with one seed and score them."""
    run = out / f"seed{seed}"
    t0 = time.perf_counter()
    single = train(run / "single", files["1_train"], a, seed)
    social = train(run / "social", files["2_train"], a, seed)
    t_train = time.perf_counter() - t0
    res: dict[str, Any] = {"seed": seed, "train_s": t_train}
    res["single_on_single"] = evaluate(single, files["1_test"], run / "eval_single_single")
    for animal in ("animal0", "animal1"):
        lab = files[f"2_test_{animal}"]
        res[f"social_on_{animal}"] = evaluate(social, lab, run / f"eval_social_{animal}")
        res[f"single_on_{animal}"] = evaluate(single, lab, run / f"eval_single_{animal}")
    base = res["single_on_single"]["P1_median"]
    res["ratio_social"] = max(res[f"social_on_{x}"]["P1_median"] / base
                              for x in ("animal0", "animal1"))  # fmt: skip
    res["ratio_single_among_animals"] = max(res[f"single_on_{x}"]["P1_median"] / base
                                            for x in ("animal0", "animal1"))  # fmt: skip
    return res


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="work and result folder")
    ap.add_argument("--frames", type=int, default=150, help="frames per session [150]")
    ap.add_argument("--train", type=int, default=2, help="training sessions per case [2]")
    ap.add_argument("--test", type=int, default=2, help="held-out sessions per case [2]")
    ap.add_argument("--size", default="320x256", help="image size WxH [320x256]")
    ap.add_argument("--steps", type=int, default=300, help="training steps [300]")
    ap.add_argument("--preset", default="small", help="network preset [small]")
    ap.add_argument("--init", default="base", help="base, scratch or a checkpoint [base]")
    ap.add_argument("--seeds", type=int, default=1, help="training seeds 0.. [1]")
    return ap


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark, print its table and record the result."""
    a = _parser().parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    files = sessions(a.out, a)
    runs = []
    for seed in range(a.seeds):
        r = run_seed(a.out, files, a, seed)
        runs.append(r)
        print(f"seed {seed}: P1 median single animal {r['single_on_single']['P1_median']:.2f} mm;"
              f" two animals, social network "
              f"{r['social_on_animal0']['P1_median']:.2f} / "
              f"{r['social_on_animal1']['P1_median']:.2f} mm (x{r['ratio_social']:.2f}), "
              f"single-animal network {r['single_on_animal0']['P1_median']:.2f} / "
              f"{r['single_on_animal1']['P1_median']:.2f} mm "
              f"(x{r['ratio_single_among_animals']:.2f})", flush=True)  # fmt: skip
    ratios = [r["ratio_social"] for r in runs]
    summary = {
        "ratio_social_median": float(np.median(ratios)),
        "ratio_social_max": float(np.max(ratios)),
        "ratio_single_among_animals_median": float(
            np.median([r["ratio_single_among_animals"] for r in runs])
        ),
    }
    print(f"== worst animal's P1 over the single-animal case: social network "
          f"x{summary['ratio_social_median']:.2f} (median over {len(runs)} seeds, max "
          f"x{summary['ratio_social_max']:.2f}; target <= 1.3), single-animal network "
          f"x{summary['ratio_single_among_animals_median']:.2f}")  # fmt: skip
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(a).items()}
    write_result("social_poses", {"settings": settings, "summary": summary, "runs": runs})
    return 0


if __name__ == "__main__":
    sys.exit(main())
