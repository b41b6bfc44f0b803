"""Temporal dynamics around the stimulation onsets.

Per-frame signals cut into trials aligned to the stimulation onsets,
and their mean over trials (the full classifier's prediction, the top variables' z-scores).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from freipose.analysis.labelled import LabelledRecording
from freipose.analysis.stats import mean_sem

DYNAMICS_COLUMNS = (
    "animal",
    "condition",
    "evaluated_on",
    "time_s",
    "mean_prediction",
    "sem_prediction",
    "mean_decision",
    "n_trials",
    "stimulated_fraction",
)
TIMECOURSE_COLUMNS = (
    "animal",
    "condition",
    "variable",
    "rank",
    "time_s",
    "mean_z",
    "sem_z",
    "n_trials",
)


def onset_aligned(
    signal: np.ndarray, windows: np.ndarray, fps: float, pre_s: float, span_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Cut a per-frame signal into trials aligned to stimulation onsets.

    Args:
        signal: (T,) or (T, D) per-frame values (NaN allowed).
        windows: (N, 2) seconds from the first frame.
        fps: frame rate of the signal.
        pre_s: seconds before onset.
        span_s: seconds after onset.

    Returns:
        time (L,) seconds relative to onset, and trials (N, L) or (N, L, D), NaN outside the
        recording.
    """
    sig = np.asarray(signal, dtype=float)
    lo, hi = int(round(pre_s * fps)), int(round(span_s * fps))
    offsets = np.arange(-lo, hi + 1)
    onset = np.round(np.asarray(windows)[:, 0] * fps).astype(np.int64)
    idx = onset[:, None] + offsets[None, :]
    valid = (idx >= 0) & (idx < sig.shape[0])
    vals = sig[np.clip(idx, 0, sig.shape[0] - 1)]
    if sig.ndim == 1:
        vals = np.where(valid, vals, np.nan)
    else:
        vals = np.where(valid[..., None], vals, np.nan)
    return offsets / fps, vals


@dataclass(frozen=True)
class PredictionTrials:
    """The full classifier's output around every stimulation onset of some recordings.

    Attributes:
        time: (L,) seconds relative to onset.
        prediction: (N, L) predicted class per trial (NaN outside a recording or undefined).
        decision: (N, L) decision value per trial.
        stimulated: (N, L) bool, True while the trial's stimulation lasts.
    """

    time: np.ndarray
    prediction: np.ndarray
    decision: np.ndarray
    stimulated: np.ndarray


def prediction_trials(
    predictions: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
    fps: float,
    pre_s: float,
    span_s: float,
) -> PredictionTrials | None:
    """Align the predictions of several recordings to their stimulation onsets.

    Args:
        predictions: per recording (prediction (T,), decision (T,), windows (W, 2)).
        fps: frame rate.
        pre_s: seconds before onset.
        span_s: seconds after onset.

    Returns:
        The trials of all recordings, or None when no recording has a window.
    """
    trials_p, trials_d, stim_masks = [], [], []
    t_rel = np.zeros(0)
    for pred, dec, windows in predictions:
        if not len(windows):
            continue
        t_rel, tp = onset_aligned(pred, windows, fps, pre_s, span_s)
        _, td = onset_aligned(dec, windows, fps, pre_s, span_s)
        trials_p.append(tp)
        trials_d.append(td)
        dur = windows[:, 1] - windows[:, 0]
        stim_masks.append((t_rel[None, :] >= 0) & (t_rel[None, :] <= dur[:, None]))
    if not trials_p:
        return None
    return PredictionTrials(
        t_rel, np.concatenate(trials_p), np.concatenate(trials_d), np.concatenate(stim_masks)
    )


def dynamics_rows(animal: str, condition: str, target: str, trials: PredictionTrials) -> list[dict]:
    """Rows of ``dynamics.csv`` for one classifier evaluated on one animal.

    Args:
        animal: the classifier's animal.
        condition: the classifier's condition.
        target: the animal whose test recordings were evaluated.
        trials: the aligned predictions.

    Returns:
        One row (columns :data:`DYNAMICS_COLUMNS`) per time step.
    """
    p = mean_sem(trials.prediction)
    d = mean_sem(trials.decision)
    sf = trials.stimulated.mean(axis=0)
    return [
        {
            "animal": animal,
            "condition": condition,
            "evaluated_on": target,
            "time_s": round(float(tt), 6),
            "mean_prediction": p.mean[j],
            "sem_prediction": p.sem[j],
            "mean_decision": d.mean[j],
            "n_trials": int(p.n[j]),
            "stimulated_fraction": float(sf[j]),
        }
        for j, tt in enumerate(trials.time)
    ]


def timecourse_rows(
    animal: str,
    condition: str,
    own: Sequence[LabelledRecording],
    train_values: np.ndarray,
    top: pd.DataFrame,
    names: Sequence[str],
    fps: float,
    pre_s: float,
    span_s: float,
) -> list[dict]:
    """Rows of ``top_variables.csv``: time courses of the top variables around onset.

    The variables are z-scored with the train frames' mean and deviation.

    Args:
        animal: the group's animal.
        condition: the group's condition.
        own: the group's test recordings.
        train_values: (N, V) the train frames' variables.
        top: the top rows of the group's attribution table (``variable``, ``rank``).
        names: (V,) the variables' names.
        fps: frame rate.
        pre_s: seconds before onset.
        span_s: seconds after onset.

    Returns:
        One row (columns :data:`TIMECOURSE_COLUMNS`) per top variable and time step.
    """
    mu = np.nanmean(train_values, axis=0)
    sd = np.nanstd(train_values, axis=0)
    sd = np.where(sd > 0, sd, 1.0)
    cols = [list(names).index(v) for v in top["variable"]]
    trials = [
        onset_aligned(
            (r.variables.values[:, cols] - mu[cols]) / sd[cols], r.windows, fps, pre_s, span_s
        )
        for r in own
        if len(r.windows)
    ]
    if not trials:
        return []
    t_rel = trials[0][0]
    allt = np.concatenate([tr for _, tr in trials])  # (N, L, D)
    rows: list[dict] = []
    for d, (vname, rank) in enumerate(zip(top["variable"], top["rank"])):
        ms = mean_sem(allt[:, :, d])
        rows.extend(
            {
                "animal": animal,
                "condition": condition,
                "variable": vname,
                "rank": int(rank),
                "time_s": round(float(tt), 6),
                "mean_z": ms.mean[j],
                "sem_z": ms.sem[j],
                "n_trials": int(ms.n[j]),
            }
            for j, tt in enumerate(t_rel)
        )
    return rows
