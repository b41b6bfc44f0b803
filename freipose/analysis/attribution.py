"""Attribution by classification (method Section 5.4.4).

For every (animal, condition) group of a study:

1. a linear SVM (``StandardScaler`` + ``LinearSVC(C, class_weight="balanced")``) on all
   variables (z-scored per recording by default, see ``AttributionConfig.standardize``) is
   trained on the group's train recordings and scored (balanced accuracy, macro
   F1, chi-squared p-value) on the group's test recordings and on the test recordings of every
   other animal with the same condition (generalization across animals;
   :mod:`freipose.analysis.classifier`);
2. its mean prediction is aligned to the stimulation onsets of those test recordings
   (temporal dynamics; :mod:`freipose.analysis.dynamics`);
3. one SVM per single variable is trained the same way and scored on the group's test
   recordings (:mod:`freipose.analysis.single`): macro F1 and a chi-squared test of
   predicted vs. true classes, with a Bonferroni correction over the variables.

Frames are labelled by :func:`freipose.analysis.study.label_frames`; frames with NaN variables
are left out of fitting and scoring (counted in the outputs). Variables undefined in every
frame of some recording (a keypoint missing throughout) are left out of the whole analysis,
and every recording needs a labelled frame with all remaining variables defined
(:mod:`freipose.analysis.usable`), so no score is computed on zero frames.

Variables that do not vary over the train frames beyond numerical noise (standard deviation
at most ``constant_rtol`` times their root mean square, see
:func:`freipose.analysis.stats.informative_columns`) are left out of the full classifier and
not tested as single variables. Standardizing such a column divides by float32 round-off: a
rigid head gives distances to the ear midpoint that are constant up to round-off within a
recording but differ between recordings (another animal or session), so the test frames get
huge z-scores and the decision function of every test frame is dominated by that one column
(the classifier predicts a single class).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import pandas as pd

from freipose.analysis.classifier import (
    CLASSIFICATION_COLUMNS,
    evaluate_on_targets,
    train_classifier,
)
from freipose.analysis.config import AttributionConfig
from freipose.analysis.dynamics import DYNAMICS_COLUMNS, TIMECOURSE_COLUMNS, timecourse_rows
from freipose.analysis.labelled import (
    LabelledRecording,
    check_test_classes,
    label_recordings,
    longest_window,
    stack_frames,
    standardized,
)
from freipose.analysis.single import attribution_table, single_variable_scores
from freipose.analysis.study import Study
from freipose.analysis.usable import drop_undefined
from freipose.analysis.variables import Variables

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class AttributionResult:
    """Tables written by ``freipose analyze``.

    Attributes:
        classification: columns :data:`~freipose.analysis.classifier.CLASSIFICATION_COLUMNS`.
        attribution: columns :data:`~freipose.analysis.single.ATTRIBUTION_COLUMNS`.
        dynamics: columns :data:`~freipose.analysis.dynamics.DYNAMICS_COLUMNS`.
        timecourses: columns :data:`~freipose.analysis.dynamics.TIMECOURSE_COLUMNS`.
        variables: layout of the variables (values of one recording).
        settings: the attribution settings.
    """

    classification: pd.DataFrame
    attribution: pd.DataFrame
    dynamics: pd.DataFrame
    timecourses: pd.DataFrame
    variables: Variables | None = None
    settings: Mapping[str, object] = field(default_factory=dict)


@dataclass(frozen=True)
class GroupResult:
    """The result rows of one (animal, condition) group.

    Attributes:
        classification: rows of ``classification.csv``.
        attribution: the group's ranked ``attribution.csv`` rows.
        dynamics: rows of ``dynamics.csv``.
        timecourses: rows of ``top_variables.csv``.
    """

    classification: list[dict]
    attribution: pd.DataFrame
    dynamics: list[dict]
    timecourses: list[dict]


OVERFIT_FIT = 0.95  # balanced accuracy on its own train frames from which a fit is "perfect"
OVERFIT_GAP = 0.1  # how far the full classifier may fall below the best single variable


def overfit_note(row: Mapping[str, Any], attribution: pd.DataFrame, n_vars: int) -> str | None:
    """A warning when the full classifier fits its train frames but not the test recordings.

    Args:
        row: the full classifier's ``classification.csv`` row on its own animal.
        attribution: the group's ``attribution.csv`` rows (single-variable scores).
        n_vars: number of variables.

    Returns:
        The warning, or None when the full classifier is not at least
        :data:`OVERFIT_GAP` below the best single variable after a near-perfect fit
        (:data:`OVERFIT_FIT`) of its train frames.
    """
    fit, test = float(row["train_balanced_accuracy"]), float(row["balanced_accuracy"])
    if attribution.empty or not fit >= OVERFIT_FIT:
        return None
    best = attribution.loc[attribution["balanced_accuracy"].idxmax()]
    if not float(best["balanced_accuracy"]) - test >= OVERFIT_GAP:
        return None
    return (
        f"    warning: the full classifier separates its train frames (balanced accuracy "
        f"{fit:.2f}) but scores {test:.2f} on the test recordings, below the best single "
        f"variable ({best['variable']}: {float(best['balanced_accuracy']):.2f}, chosen on "
        f"those frames): on {n_vars} variables it has learned chance features of the train "
        "recordings. Record more stimulation trials; and if the train recordings' frames "
        "trained the pose network, their poses are cleaner than the test recordings' "
        "(docs/own-data.md, section 9)"
    )


def analyze_group(
    study: Study,
    recs: dict[str, LabelledRecording],
    layout: Variables,
    animal: str,
    condition: str,
    config: AttributionConfig,
    span_s: float,
    say: Callable[[str], None],
    prefix: str = "",
) -> GroupResult:
    """Full classifier, single-variable SVMs and time courses of one group.

    Args:
        study: the study.
        recs: recording name -> labelled recording (all with the same variables).
        layout: the variables of the first recording (names, frame rate).
        animal: the group's animal.
        condition: the group's condition.
        config: the attribution settings.
        span_s: seconds after onset of the dynamics window.
        say: progress messages.
        prefix: start of the first progress message (e.g. ``"[1/2] "``).

    Returns:
        The group's result rows.
    """
    names = layout.names
    train_recs = [recs[r.name] for r in study.select(animal, condition, "train")]
    train = stack_frames(train_recs, config.train_stride)
    clf = train_classifier(train, config, animal, condition, len(names), say, prefix)
    full = evaluate_on_targets(clf, study, recs, animal, condition, config, layout.fps, span_s, say)
    own = [recs[r.name] for r in study.select(animal, condition, "test")]
    test = stack_frames(own)
    res = single_variable_scores(
        train.values,
        train.labels,
        test.values,
        test.labels,
        test.recording,
        config,
        desc=f"{animal}/{condition} single-variable SVMs",
    )
    df = attribution_table(animal, condition, res, layout, config)
    say(
        f"    single variables: {int(df['significant'].sum())} of {len(names)} significant "
        f"(p_adjusted < {config.alpha}); best {df['variable'].iloc[0]} "
        f"F1 {df['f1'].iloc[0]:.3f}"
    )
    note = overfit_note(full.classification[0], df, len(names))
    if note:
        say(note)
    top = df.head(config.top)
    tc = timecourse_rows(
        animal, condition, own, train.values, top, names, layout.fps, config.pre_s, span_s
    )
    return GroupResult(full.classification, df, full.dynamics, tc)


def run_attribution(
    study: Study,
    variables: Mapping[str, Variables],
    config: AttributionConfig = AttributionConfig(),
    log_fn: Callable[[str], None] | None = None,
) -> AttributionResult:
    """Classification, attribution and dynamics for every (animal, condition) group.

    Args:
        study: the validated study.
        variables: recording name -> its variables (all with the same layout and fps).
        config: the attribution settings.
        log_fn: progress messages (default: this module's logger).

    Returns:
        The four result tables.

    Raises:
        NoUsableFramesError: a recording has no usable frame (see
            :func:`~freipose.analysis.usable.drop_undefined`).
        StudyError: an animal's test recordings of a condition lack stimulated or
            not-stimulated frames (see :func:`~freipose.analysis.labelled.check_test_classes`).
    """
    say = log_fn or log.info
    recs = drop_undefined(label_recordings(study, variables, config), study.path)
    check_test_classes(recs)
    if config.standardize == "recording":
        recs = standardized(recs, config.constant_rtol)
    layout = next(iter(recs.values())).variables
    span = longest_window(recs) + config.post_s
    n_groups = len(study.groups)
    groups = [
        analyze_group(study, recs, layout, animal, cond, config, span, say, f"[{gi}/{n_groups}] ")
        for gi, (animal, cond) in enumerate(study.groups, start=1)
    ]
    return AttributionResult(
        classification=pd.DataFrame(
            [row for g in groups for row in g.classification], columns=list(CLASSIFICATION_COLUMNS)
        ),
        attribution=pd.concat([g.attribution for g in groups], ignore_index=True),
        dynamics=pd.DataFrame(
            [row for g in groups for row in g.dynamics], columns=list(DYNAMICS_COLUMNS)
        ),
        timecourses=pd.DataFrame(
            [row for g in groups for row in g.timecourses], columns=list(TIMECOURSE_COLUMNS)
        ),
        variables=layout,
        settings={k: getattr(config, k) for k in config.__dataclass_fields__},
    )
