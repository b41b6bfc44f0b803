"""Study design: how many stimulation trials and animals find an effect on one variable.

A pilot study (recordings with their events, as for ``freipose analyze``) gives, for one
variable, its trials: each stimulation window with the frames around it, from the middle
of the pause before the window to the middle of the pause after it (the first and last
trial reach the start and end of the recording). Each trial has an *effect*, the mean of
the variable (z-scored per recording) over its stimulated frames minus the mean over its
not-stimulated frames, and a *residual*, the trial's series with that effect taken out of
its stimulated frames; the residual keeps the variable's own noise and autocorrelation.

A simulated study of ``n`` trials per animal draws, for every animal, a pilot animal and
``n`` of its trials with replacement, adds the chosen effect (the pilot's mean effect or
a given size, plus each drawn trial's deviation from the pilot's mean) to their
stimulated frames, and cuts them into recordings of as many trials as a pilot recording
holds (the first half of the trials train, the rest test), each z-scored on its own. Each
animal then gets the test of ``freipose analyze``: the single-variable SVM trained on the
train recordings and scored on the test recordings
(:func:`freipose.analysis.single.fit_block`, effective frames per recording), its p-value
Bonferroni-adjusted over the pilot's number of tested variables, significant below
``alpha`` with a balanced accuracy above 0.5. The power is the share of simulated studies
in which the variable is significant in every animal.
"""

from __future__ import annotations

import difflib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from freipose.analysis.config import AttributionConfig
from freipose.analysis.labelled import LabelledRecording, label_recordings, standardized
from freipose.analysis.single import fit_block
from freipose.analysis.stats import informative_columns
from freipose.analysis.study import IGNORED, NOT_STIMULATED, STIMULATED, Study, StudyError
from freipose.analysis.usable import drop_undefined
from freipose.analysis.variables import Variables

DESIGN_COLUMNS = ("trials", "animals", "power", "power_low", "power_high", "power_per_animal")


@dataclass(frozen=True, eq=False)
class Trial:
    """One pilot trial of one variable.

    Attributes:
        animal: the pilot animal.
        residual: (L,) z-scored values with the trial's effect taken out of its stimulated
            frames (NaN where undefined).
        labels: (L,) frame labels (stimulated, not stimulated or ignored).
        effect: mean over the stimulated frames minus mean over the not-stimulated ones.
    """

    animal: str
    residual: np.ndarray
    labels: np.ndarray
    effect: float


@dataclass(frozen=True, eq=False)
class Pilot:
    """The trials of one variable in a pilot study.

    Attributes:
        variable: the variable's name.
        trials: the trials with both stimulated and not-stimulated frames.
        n_tested: the variables the analysis would test (the Bonferroni family's size).
        per_recording: trials of a pilot recording (median); simulated recordings hold
            as many.
    """

    variable: str
    trials: tuple[Trial, ...]
    n_tested: int
    per_recording: int = 1

    @property
    def mean_effect(self) -> float:
        """The mean effect over the trials (z units)."""
        return float(np.mean([t.effect for t in self.trials]))

    @property
    def animals(self) -> tuple[str, ...]:
        """The pilot animals, in order of first appearance."""
        return tuple(dict.fromkeys(t.animal for t in self.trials))


def variable_index(names: Sequence[str], variable: str) -> int:
    """The column of ``variable``, with the closest names in the error.

    Raises:
        StudyError: no such variable.
    """
    if variable in names:
        return list(names).index(variable)
    close = difflib.get_close_matches(variable, list(names), n=5, cutoff=0.5)
    hint = f"; close names: {', '.join(close)}" if close else ""
    raise StudyError(
        f"no variable {variable!r} among the {len(names)} variables of the pilot's poses"
        f"{hint} (attribution.csv of an analysis lists them all)"
    )


def _cuts(rec: LabelledRecording) -> list[tuple[int, int]]:
    """Frame ranges of the trials of one recording (see the module docstring)."""
    t = rec.variables.times
    win = rec.windows
    if not len(win):
        return []
    mids = (win[1:, 0] + win[:-1, 1]) / 2
    bounds = np.concatenate([[t[0]], mids, [t[-1] + 1.0]])
    idx = np.searchsorted(t, bounds, side="left")
    return [(int(idx[i]), int(idx[i + 1])) for i in range(len(win))]


def pilot_trials(
    study: Study,
    variables: Mapping[str, Variables],
    variable: str,
    config: AttributionConfig = AttributionConfig(),
) -> Pilot:
    """Cut every recording of a pilot study into the trials of one variable.

    Args:
        study: the pilot study (both splits are used).
        variables: recording name -> its variables.
        variable: the variable's name.
        config: the labelling (onset delay, margin) and standardization of the analysis.

    Returns:
        The pilot's trials of that variable.

    Raises:
        StudyError: no such variable, or no trial with stimulated and not-stimulated frames.
    """
    recs = drop_undefined(label_recordings(study, variables, config), study.path)
    if config.standardize == "recording":
        recs = standardized(recs, config.constant_rtol)
    first = next(iter(recs.values())).variables
    j = variable_index(first.names, variable)
    trials = []
    counts = []
    for rec in recs.values():
        x = rec.variables.values[:, j].astype(np.float64)
        counts.append(len(_cuts(rec)))
        for a, b in _cuts(rec):
            xs, ys = x[a:b], rec.labels[a:b]
            on, off = (ys == STIMULATED) & np.isfinite(xs), (ys == NOT_STIMULATED) & np.isfinite(xs)
            if not on.any() or not off.any():
                continue
            d = float(xs[on].mean() - xs[off].mean())
            trials.append(Trial(rec.recording.animal, xs - d * (ys == STIMULATED), ys, d))
    if not trials:
        raise StudyError(
            f"the pilot study {study.path} has no stimulation window with stimulated and "
            f"not-stimulated frames of {variable!r} around it; check its events files, "
            "--onset-delay and --margin"
        )
    values = np.concatenate([r.variables.values for r in recs.values()])
    n_tested = int(informative_columns(values).sum())
    return Pilot(variable, tuple(trials), n_tested, int(np.median(counts)))


def _split(
    trials: Sequence[Trial], effect: float, pilot: Pilot, config: AttributionConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Recordings of ``pilot.per_recording`` trials each, with ``effect`` on stimulated frames.

    Each recording is z-scored on its own (with ``standardize = "recording"``) and its
    ignored frames dropped, as the analysis does.

    Returns:
        (N,) values, (N,) labels in {0, 1} and (N,) recording index of the kept frames.
    """
    xs, ys, ids = [], [], []
    m, k = pilot.mean_effect, max(1, pilot.per_recording)
    for r, a in enumerate(range(0, len(trials), k)):
        part = trials[a : a + k]
        x = np.concatenate([t.residual + (effect + t.effect - m) * (t.labels == STIMULATED)
                            for t in part])  # fmt: skip
        y = np.concatenate([t.labels for t in part])
        if config.standardize == "recording":
            x = _zscore(x)
        keep = y != IGNORED
        xs.append(x[keep])
        ys.append(y[keep])
        ids.append(np.full(int(keep.sum()), r, dtype=np.int64))
    return np.concatenate(xs), np.concatenate(ys).astype(np.int8), np.concatenate(ids)


def _zscore(x: np.ndarray) -> np.ndarray:
    ok = np.isfinite(x)
    sd = x[ok].std() if ok.sum() > 1 else 0.0
    return (x - x[ok].mean()) / sd if sd > 0 else np.zeros_like(x)


def animal_significant(
    pilot: Pilot,
    trials: int,
    effect: float,
    rng: np.random.Generator,
    config: AttributionConfig,
) -> bool:
    """Simulate one animal of ``trials`` trials and run the analysis' single-variable test.

    Args:
        pilot: the pilot's trials.
        trials: trials of the animal (the first half trains, the rest tests; at least 2).
        effect: the effect added to the stimulated frames (z units).
        rng: random draws of the pilot animal and its trials.
        config: SVM, significance level and standardization.

    Returns:
        Whether the variable is significant in this animal.
    """
    animals = pilot.animals
    animal = animals[int(rng.integers(len(animals)))]
    own = [t for t in pilot.trials if t.animal == animal]
    drawn = [own[int(i)] for i in rng.integers(len(own), size=trials)]
    half = max(1, trials // 2)
    xtr, ytr, _ = _split(drawn[:half], effect, pilot, config)
    xte, yte, rec = _split(drawn[half:], effect, pilot, config)
    if len(np.unique(ytr)) < 2 or len(np.unique(yte)) < 2:
        return False
    f1, p, ba, *_ = fit_block(
        xtr[:, None], ytr, xte[:, None], yte, rec, config.C, config.max_iter,
        config.constant_rtol,
    )[0]  # fmt: skip
    return bool(min(1.0, p * max(pilot.n_tested, 1)) < config.alpha and ba > 0.5)


def power_table(
    pilot: Pilot,
    trials: Sequence[int],
    animals: Sequence[int],
    effect: float | None = None,
    simulations: int = 200,
    config: AttributionConfig = AttributionConfig(),
    seed: int = 0,
) -> pd.DataFrame:
    """The power of every design (trials per animal x animals) by simulation.

    Args:
        pilot: the pilot's trials.
        trials: trials per animal to try (each at least 2).
        animals: numbers of animals to try.
        effect: the effect to detect in z units (standard deviations of the variable in a
            recording); None: the pilot's mean effect.
        simulations: simulated studies per design.
        config: the analysis settings (the test's ``alpha``).
        seed: random seed.

    Returns:
        Columns :data:`DESIGN_COLUMNS`: the power (the variable significant in every animal)
        with its 95 % Clopper-Pearson interval, and the share of significant animals.

    Raises:
        StudyError: fewer than 2 trials, no animal or no simulation.
    """
    from scipy.stats import beta

    if min(trials, default=0) < 2 or min(animals, default=0) < 1 or simulations < 1:
        raise StudyError(
            f"a design needs at least 2 trials per animal (train and test), 1 animal and 1 "
            f"simulation; got trials {list(trials)}, animals {list(animals)}, "
            f"{simulations} simulations"
        )
    eff = pilot.mean_effect if effect is None else float(effect)
    rng = np.random.default_rng(seed)
    rows = []
    n_max = max(animals)
    for n in trials:
        hits = np.array([[animal_significant(pilot, n, eff, rng, config) for _ in range(n_max)]
                         for _ in range(simulations)])  # fmt: skip
        for a in animals:
            k = int(hits[:, :a].all(axis=1).sum())
            lo = float(beta.ppf(0.025, k, simulations - k + 1)) if k else 0.0
            hi = float(beta.ppf(0.975, k + 1, simulations - k)) if k < simulations else 1.0
            rows.append((n, a, k / simulations, lo, hi, float(hits[:, :a].mean())))
    return pd.DataFrame(rows, columns=list(DESIGN_COLUMNS))


def recommended(table: pd.DataFrame, target: float) -> dict[int, int | None]:
    """The fewest trials per animal whose power reaches ``target``, for each animal count.

    Args:
        table: :func:`power_table`'s rows.
        target: the power wanted (e.g. 0.8).

    Returns:
        animals -> trials per animal (None: no tried number reaches it).
    """
    out: dict[int, int | None] = {}
    for a, rows in table.groupby("animals", sort=True):
        ok = rows[rows["power"] >= target]
        out[int(a)] = int(ok["trials"].min()) if len(ok) else None
    return out
