"""Benchmark: the family-wise false-positive rate of ``freipose analyze`` on null studies.

Each null study holds several animals with a train and a test recording each: poses of the
synthetic rat behaving freely (:func:`freipose.synth.simulate_trajectory`, no stimulation
effect) with stimulation windows that change nothing. The studies draw their recordings
from a pool of such recordings per design (``--pool``; the stimulation schedules are new in
every study, so every study is a null study), or simulate new poses for every recording
with ``--pool 0``. Half of the studies use a sparse design (60 s recordings, 5 s windows
at irregular intervals of about 15 s), half the demo's periodic train (30 s recordings,
2 s on, 2 s off). The studies run the analysis of ``freipose analyze``
(:func:`freipose.analysis.attribution.run_attribution`, variables as ``compute_variables``
gives them); a study is a false positive when any single variable of any of its animals is
called significant. The script prints the share of such studies with its exact
(Clopper-Pearson) 95 % interval, at the analysis' significance level and at 0.05.

    python benchmarks/null_studies.py [--studies 100] [--animals 2] [--pool 24] [--seed 0]
"""

from __future__ import annotations

import argparse
import io
import os
import tempfile
import time
from contextlib import redirect_stderr
from dataclasses import dataclass, replace
from pathlib import Path

from _results import write_result

FPS = 25.0
STFT_WINDOW = 16


@dataclass(frozen=True)
class Design:
    """A stimulation design of the null studies.

    Attributes:
        name: the design's name.
        duration_s: length of every recording.
        length_s: length of a window.
        period_s: mean interval between window starts.
        jitter_s: largest change of an interval.
        onset_delay_s: the analysis' onset delay.
        margin_s: the analysis' margin.
    """

    name: str
    duration_s: float
    length_s: float
    period_s: float
    jitter_s: float
    onset_delay_s: float
    margin_s: float


DESIGNS = (
    Design("sparse", 60.0, 5.0, 15.0, 4.0, 0.4, 1.5),
    Design("periodic", 30.0, 2.0, 4.0, 0.0, 0.6, 0.5),
)


def recording_variables(design: Design, seed: int):
    """The variables of one recording of the freely behaving synthetic rat."""
    import numpy as np

    from freipose.analysis.floor import FloorPlane
    from freipose.analysis.variables import VariableConfig, compute_variables
    from freipose.skeleton import load_skeleton
    from freipose.synth import simulate_trajectory

    n = int(design.duration_s * FPS)
    poses = simulate_trajectory(n, FPS, seed).astype(np.float32)
    floor = FloorPlane.world([0.0, 0.0, 1.0])
    vcfg = VariableConfig(stft_window=STFT_WINDOW)
    return compute_variables(poses, np.arange(n), FPS, load_skeleton("rat"), floor, vcfg)


def null_study(folder: Path, design: Design, animals: int, seed: int, pool: list | None):
    """The recordings and variables of one null study.

    Args:
        folder: where the events files go.
        design: the stimulation design.
        animals: animals of the study (a train and a test recording each).
        seed: random seed of the schedules and poses.
        pool: variables of recordings to draw from (distinct ones per study); None: new
            poses for every recording.

    Returns:
        (study, variables by recording name).
    """
    import numpy as np

    from freipose.analysis.simulate import stimulation_windows, write_events_csv
    from freipose.analysis.study import Recording, Study

    rng = np.random.default_rng(seed)
    picks = rng.choice(len(pool), 2 * animals, replace=False) if pool else None
    recs, variables = [], {}
    for i in range(2 * animals):
        a, split = i // 2, ("train", "test")[i % 2]
        name = f"rat{a + 1}_{split}"
        first = rng.uniform(1.0, 1.0 + design.period_s)
        win = stimulation_windows(
            design.duration_s, first, design.period_s, design.length_s, design.jitter_s,
            seed=int(rng.integers(2**31)),
        )  # fmt: skip
        events = folder / f"{name}_events.csv"
        write_events_csv(win, events)
        if picks is None:
            variables[name] = recording_variables(design, int(rng.integers(2**31)))
        else:
            variables[name] = pool[int(picks[i])]
        recs.append(Recording(name, folder / f"{name}.poses.h5", events, f"rat{a + 1}",
                              design.name, split))  # fmt: skip
    return Study(folder / "study.toml", tuple(recs)), variables


def interval(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """The exact (Clopper-Pearson) interval of a share of ``k`` in ``n``."""
    from scipy.stats import beta

    a = (1 - level) / 2
    lo = 0.0 if k == 0 else float(beta.ppf(a, k, n - k + 1))
    hi = 1.0 if k == n else float(beta.ppf(1 - a, k + 1, n - k))
    return lo, hi


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--studies", type=int, default=100, help="null studies (half per design)")
    ap.add_argument("--animals", type=int, default=2, help="animals per study")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--pool",
        type=int,
        default=24,
        help="recordings of free behaviour per design that the studies draw from (their "
        "schedules are new in every study); 0: new poses for every recording (slower)",
    )
    args = ap.parse_args()
    if args.studies < 1 or args.animals < 1:
        ap.error("--studies and --animals must be at least 1")
    if 0 < args.pool < 2 * args.animals:
        ap.error(f"--pool must be 0 or at least 2 x --animals ({2 * args.animals})")
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")

    from freipose.analysis.attribution import run_attribution
    from freipose.analysis.config import AttributionConfig

    base = AttributionConfig()
    t0 = time.perf_counter()
    hits = {"alpha": 0, "0.05": 0}
    per_design = {d.name: [0, 0] for d in DESIGNS}
    pools = {
        d.name: [recording_variables(d, args.seed * 7919 + j) for j in range(args.pool)]
        if args.pool
        else None
        for d in DESIGNS
    }
    for i in range(args.studies):
        design = DESIGNS[i % len(DESIGNS)]
        cfg = replace(base, onset_delay_s=design.onset_delay_s, margin_s=design.margin_s)
        with tempfile.TemporaryDirectory() as tmp, redirect_stderr(io.StringIO()):
            seed = args.seed * 100003 + i
            study, variables = null_study(Path(tmp), design, args.animals, seed, pools[design.name])
            res = run_attribution(study, variables, cfg, log_fn=lambda _: None)
        att = res.attribution
        above = att["balanced_accuracy"] > 0.5
        p = float(att.loc[above, "p_adjusted"].min()) if above.any() else 1.0
        hit = bool(att["significant"].any())
        hits["alpha"] += hit
        hits["0.05"] += p < 0.05
        per_design[design.name][0] += hit
        per_design[design.name][1] += 1
        print(f"study {i + 1}/{args.studies} ({design.name}): smallest adjusted p {p:.3g}"
              + (" SIGNIFICANT" if hit else ""), flush=True)  # fmt: skip
    n = args.studies
    wall = time.perf_counter() - t0
    figures = {"studies": n, "animals": args.animals, "alpha": base.alpha,
               "wall_s": round(wall, 1)}  # fmt: skip
    for key, level in (("alpha", base.alpha), ("0.05", 0.05)):
        k = hits[key]
        lo, hi = interval(k, n)
        print(f"family-wise false-positive rate at level {level:g}: {k}/{n} = {k / n:.1%} "
              f"(95 % interval {lo:.1%} to {hi:.1%})")  # fmt: skip
        tag = "at_alpha" if key == "alpha" else "at_0.05"
        figures[f"fwer_{tag}"] = k / n
        figures[f"fwer_{tag}_ci"] = f"{lo:.3f}-{hi:.3f}"
    for name, (k, m) in per_design.items():
        figures[f"fwer_at_alpha_{name}"] = k / m if m else float("nan")
    print(f"{n} null studies in {wall:.0f} s")
    write_result("null_studies", figures, extra={"seed": args.seed, "pool": args.pool})


if __name__ == "__main__":
    main()
