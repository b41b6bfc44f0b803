"""The full classifier of a group.

A linear SVM on all informative variables, trained on the
group's train recordings and evaluated on the test recordings of the group's animal and of
every other animal with the same condition (generalization across animals).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from freipose.analysis.config import AttributionConfig
from freipose.analysis.dynamics import PredictionTrials, dynamics_rows, prediction_trials
from freipose.analysis.labelled import Frames, LabelledRecording
from freipose.analysis.stats import informative_columns, scores
from freipose.analysis.study import IGNORED, Study, StudyError

CLASSIFICATION_COLUMNS = (
    "animal",
    "condition",
    "evaluated_on",
    "balanced_accuracy",
    "f1",
    "n_frames",
    "n_stimulated",
    "p_value",
    "n_effective",
    "n_train_frames",
    "n_train_nan_excluded",
    "n_variables_used",
    "train_balanced_accuracy",
)


def make_svm(C: float, max_iter: int = 10000) -> Any:
    """StandardScaler + LinearSVC(C, class_weight="balanced"), seeded.

    liblinear's dual solver (used when there are more variables than frames) visits the
    frames in a random order; the seed makes the fit reproducible.

    Args:
        C: SVM regularization.
        max_iter: LinearSVC iteration limit.

    Returns:
        An unfitted scikit-learn pipeline.
    """
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler
    from sklearn.svm import LinearSVC

    return make_pipeline(
        StandardScaler(),
        LinearSVC(C=C, class_weight="balanced", dual="auto", max_iter=max_iter, random_state=0),
    )


def predict_frames(model: Any, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame decision value and predicted class.

    Args:
        model: a fitted classifier with ``decision_function``.
        values: (T, V) variables.

    Returns:
        (T,) decision values and (T,) predicted classes (as float), NaN where a variable is
        NaN.
    """
    ok = np.isfinite(values).all(axis=1)
    dec = np.full(len(values), np.nan)
    if ok.any():
        dec[ok] = model.decision_function(values[ok])
    pred = np.where(ok, (dec > 0).astype(float), np.nan)
    return dec, pred


@dataclass(frozen=True, eq=False)
class GroupClassifier:
    """The full classifier of one (animal, condition) group.

    Attributes:
        model: the fitted scikit-learn pipeline.
        columns: (U,) indices of the variables it uses.
        n_train: number of train frames it was fitted on.
        n_nan: train frames left out because a used variable is NaN.
        train_balanced_accuracy: its balanced accuracy on the frames it was fitted on.
    """

    model: Any
    columns: np.ndarray
    n_train: int
    n_nan: int
    train_balanced_accuracy: float


def train_classifier(
    train: Frames,
    config: AttributionConfig,
    animal: str,
    condition: str,
    num_variables: int,
    say: Callable[[str], None],
    prefix: str = "",
) -> GroupClassifier:
    """Fit the full classifier on a group's train frames.

    Columns constant up to round-off (or undefined) in the train frames carry no
    information and would blow up under standardization: they are left out.

    Args:
        train: the group's train frames.
        config: C, iteration limit and constant threshold.
        animal: the group's animal (for messages).
        condition: the group's condition (for messages).
        num_variables: number of variables V (for messages).
        say: progress messages.
        prefix: start of the progress message (e.g. ``"[1/2] "``).

    Returns:
        The fitted classifier.

    Raises:
        StudyError: no variable varies, or the train frames lack one of the two classes.
    """
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.metrics import balanced_accuracy_score

    cols = np.flatnonzero(informative_columns(train.values, config.constant_rtol))
    if len(cols) == 0:
        raise StudyError(
            f"group (animal {animal!r}, condition {condition!r}): no variable varies over the "
            f"train frames (all {num_variables} are constant or undefined); check the poses "
            f"of the train recordings"
        )
    fin = np.isfinite(train.values[:, cols]).all(axis=1)
    xtr, ytr = train.values[fin][:, cols], train.labels[fin]
    n_nan = int((~fin).sum())
    counts = np.bincount(ytr, minlength=2)
    if counts.min() == 0:
        raise StudyError(
            f"group (animal {animal!r}, condition {condition!r}): the train recordings have "
            f"{counts[1]} stimulated and {counts[0]} not-stimulated usable frames; both are "
            f"needed (check the events files, --onset-delay and --margin, and missing poses)"
        )
    say(
        f"{prefix}{animal} / {condition}: training on {len(ytr)} frames "
        f"({counts[1]} stimulated; {n_nan} with undefined variables left out) on "
        f"{len(cols)} of {num_variables} variables ({num_variables - len(cols)} constant or "
        f"undefined over the train frames left out)"
    )
    model = make_svm(config.C, config.max_iter)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        model.fit(xtr, ytr)
    fitted = float(balanced_accuracy_score(ytr, model.predict(xtr)))
    return GroupClassifier(model, cols, int(len(ytr)), n_nan, fitted)


def evaluation_targets(study: Study, animal: str, condition: str) -> list[str]:
    """Animals whose test recordings a group's classifier is evaluated on.

    Args:
        study: the study.
        animal: the group's animal.
        condition: the group's condition.

    Returns:
        The group's own animal first, then the other animals with test recordings of the
        same condition, sorted.
    """
    others = {r.animal for r in study.recordings if r.condition == condition and r.split == "test"}
    return [animal] + sorted(others - {animal})


@dataclass(frozen=True)
class Evaluation:
    """A classifier evaluated on the test recordings of one animal.

    Attributes:
        row: the ``classification.csv`` row (columns :data:`CLASSIFICATION_COLUMNS`).
        trials: its predictions around the stimulation onsets, None without windows.
    """

    row: dict
    trials: PredictionTrials | None


def evaluate_classifier(
    clf: GroupClassifier,
    tests: Sequence[LabelledRecording],
    animal: str,
    condition: str,
    target: str,
    config: AttributionConfig,
    fps: float,
    span_s: float,
) -> Evaluation:
    """Score a group's classifier on test recordings (frames with NaN variables left out).

    Args:
        clf: the group's classifier.
        tests: the test recordings of ``target`` with the group's condition.
        animal: the group's animal.
        condition: the group's condition.
        target: the evaluated animal.
        config: significance test and dynamics window.
        fps: frame rate.
        span_s: seconds after onset of the dynamics window.

    Returns:
        The classification row and the aligned predictions.
    """
    ys, ps, segs, preds = [], [], [], []
    for r in tests:
        dec, pred = predict_frames(clf.model, r.variables.values[:, clf.columns])
        m = (r.labels != IGNORED) & np.isfinite(pred)
        ys.append(r.labels[m])
        ps.append(pred[m])
        segs.append(int(m.sum()))
        preds.append((pred, dec, r.windows))
    y, p = np.concatenate(ys).astype(int), np.concatenate(ps).astype(int)
    ba, f1, pv_naive, n_eff, pv = scores(y, p, np.array(segs))
    if config.independent_frames:
        pv = pv_naive
    row = {
        "animal": animal,
        "condition": condition,
        "evaluated_on": target,
        "balanced_accuracy": ba,
        "f1": f1,
        "n_frames": int(len(y)),
        "n_stimulated": int(y.sum()),
        "p_value": pv,
        "n_effective": n_eff,
        "n_train_frames": clf.n_train,
        "n_train_nan_excluded": clf.n_nan,
        "n_variables_used": int(len(clf.columns)),
        "train_balanced_accuracy": clf.train_balanced_accuracy,
    }
    return Evaluation(row, prediction_trials(preds, fps, config.pre_s, span_s))


@dataclass(frozen=True)
class GroupEvaluation:
    """A group's classifier evaluated on every target animal.

    Attributes:
        classification: rows of ``classification.csv``, one per target.
        dynamics: rows of ``dynamics.csv``.
    """

    classification: list[dict]
    dynamics: list[dict]


def evaluate_on_targets(
    clf: GroupClassifier,
    study: Study,
    recs: dict[str, LabelledRecording],
    animal: str,
    condition: str,
    config: AttributionConfig,
    fps: float,
    span_s: float,
    say: Callable[[str], None],
) -> GroupEvaluation:
    """Evaluate a group's classifier on its own animal and every other animal.

    Args:
        clf: the group's classifier.
        study: the study.
        recs: recording name -> labelled recording.
        animal: the group's animal.
        condition: the group's condition.
        config: significance test and dynamics window.
        fps: frame rate.
        span_s: seconds after onset of the dynamics window.
        say: progress messages.

    Returns:
        The ``classification.csv`` and ``dynamics.csv`` rows.
    """
    cls_rows: list[dict] = []
    dyn_rows: list[dict] = []
    for target in evaluation_targets(study, animal, condition):
        names = [r.name for r in study.select(target, condition, "test")]
        tests = [recs[n] for n in names]
        ev = evaluate_classifier(clf, tests, animal, condition, target, config, fps, span_s)
        cls_rows.append(ev.row)
        say(
            f"    evaluated on {target}'s test recordings ({', '.join(names)}): "
            f"balanced accuracy {ev.row['balanced_accuracy']:.3f}, "
            f"F1 {ev.row['f1']:.3f}, {ev.row['n_frames']} frames"
        )
        if ev.trials is not None:
            dyn_rows.extend(dynamics_rows(animal, condition, target, ev.trials))
    return GroupEvaluation(cls_rows, dyn_rows)
