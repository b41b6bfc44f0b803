"""Attribution by classification (method Section 5.4.4).

For every (animal, condition) group of a study:

1. a linear SVM (``StandardScaler`` + ``LinearSVC(C, class_weight="balanced")``) on all
   variables (z-scored per recording by default, see ``AttributionConfig.standardize``) is
   trained on the group's train recordings and scored (balanced accuracy, macro
   F1, chi-squared p-value) on the group's test recordings and on the test recordings of every
   other animal with the same condition (generalization across animals);
2. its mean prediction is aligned to the stimulation onsets of those test recordings
   (temporal dynamics);
3. one SVM per single variable is trained the same way and scored on the group's test
   recordings: macro F1 and a chi-squared test of predicted vs. true classes, with a
   Bonferroni correction over the variables. A variable is *significant* when its adjusted
   p-value is below ``alpha`` and it does better than chance (balanced accuracy > 0.5); a
   classifier that is reliably wrong is not an effect of the stimulation on that variable.

Frames are labelled by :func:`freipose.analysis.study.label_frames`; frames with NaN variables
are left out of fitting and scoring (counted in the outputs).

Variables that do not vary over the train frames beyond numerical noise (standard deviation
at most ``constant_rtol`` times their root mean square, see :func:`informative_columns`) are
left out of the full classifier and not tested as single variables. Standardizing such a
column divides by float32 round-off: a rigid head gives distances to the ear midpoint that are
constant up to ~1e-6 mm within a recording but differ between recordings (another animal or
session), so the test frames get z-scores of ~1e6 and the decision function of every test
frame is dominated by that one column (the classifier predicts a single class).
"""

from __future__ import annotations

import dataclasses
import logging
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from freipose.analysis.study import (
    IGNORED,
    Recording,
    Study,
    StudyError,
    check_windows,
    label_frames,
    read_events,
)
from freipose.analysis.variables import Variables

log = logging.getLogger(__name__)

CLASSIFICATION_COLUMNS = [
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
]
ATTRIBUTION_COLUMNS = [
    "animal",
    "condition",
    "rank",
    "variable",
    "keypoints",
    "f1",
    "p_value",
    "p_adjusted",
    "significant",
    "balanced_accuracy",
    "type",
    "part",
    "n_frames",
    "n_effective",
    "p_value_independent",
]
DYNAMICS_COLUMNS = [
    "animal",
    "condition",
    "evaluated_on",
    "time_s",
    "mean_prediction",
    "sem_prediction",
    "mean_decision",
    "n_trials",
    "stimulated_fraction",
]
TIMECOURSE_COLUMNS = [
    "animal",
    "condition",
    "variable",
    "rank",
    "time_s",
    "mean_z",
    "sem_z",
    "n_trials",
]


STANDARDIZE = ("recording", "train")


@dataclass(frozen=True)
class AttributionConfig:
    """Settings of :func:`run_attribution` (defaults follow the method).

    Attributes:
        C: SVM regularization (method: 0.0025).
        onset_delay_s: frames from ``start + onset_delay_s`` to ``end`` are stimulated.
        margin_s: frames further than this from every window are not stimulated.
        alpha: significance level for Bonferroni-adjusted p-values (method figure: 0.001).
        n_jobs: parallel workers for the single-variable SVMs (joblib; -1 = all cores).
        train_stride: use every n-th labelled train frame (frames are strongly correlated).
        pre_s, post_s: dynamics window from ``pre_s`` before onset to ``post_s`` after offset.
        top: number of top variables whose time courses are reported.
        max_iter: LinearSVC iteration limit.
        block: variables per parallel task.
        independent_frames: test significance counting every frame as an independent
            sample, as the method did (anti-conservative: consecutive frames are correlated);
            by default the chi-squared test uses the effective number of independent frames.
        constant_rtol: a variable whose standard deviation over the train frames is at most
            this fraction of its root mean square is constant up to numerical noise and is
            not used (1e-5: about 100 float32 round-offs; see :func:`informative_columns`).
        standardize: "recording" (default) z-scores every variable of every recording with
            that recording's own mean and deviation over all its frames before fitting and
            scoring, which removes offsets between recordings (animal size, camera setup)
            that a variable with little variation in the train recording would otherwise
            turn into a constant decision; "train" standardizes with the train frames'
            statistics only (the method's ``StandardScaler``).
    """

    C: float = 0.0025
    onset_delay_s: float = 0.4
    margin_s: float = 1.5
    alpha: float = 0.001
    n_jobs: int = 1
    train_stride: int = 1
    pre_s: float = 5.0
    post_s: float = 5.0
    top: int = 6
    max_iter: int = 10000
    block: int = 16
    independent_frames: bool = False
    constant_rtol: float = 1e-5
    standardize: str = "recording"

    def __post_init__(self) -> None:
        if self.standardize not in STANDARDIZE:
            raise ValueError(
                f"standardize must be one of {', '.join(STANDARDIZE)}, got {self.standardize!r}"
            )
        if not 0 <= self.constant_rtol < 1:
            raise ValueError(f"constant_rtol must be in [0, 1), got {self.constant_rtol}")
        if not self.C > 0:
            raise ValueError(f"C must be > 0, got {self.C}")
        if not 0 < self.alpha < 1:
            raise ValueError(f"alpha must be in (0, 1), got {self.alpha}")
        if self.train_stride < 1:
            raise ValueError(f"train_stride must be >= 1, got {self.train_stride}")
        if self.pre_s < 0 or self.post_s < 0:
            raise ValueError("pre_s and post_s must be >= 0 seconds")
        if self.onset_delay_s < 0 or self.margin_s < 0:
            raise ValueError("onset_delay_s and margin_s must be >= 0 seconds")


@dataclass(frozen=True, eq=False)
class LabelledRecording:
    """A recording's variables, stimulation windows and frame labels."""

    recording: Recording
    variables: Variables
    windows: np.ndarray
    labels: np.ndarray


@dataclass(frozen=True, eq=False)
class AttributionResult:
    """Tables written by ``freipose analyze`` (columns as in ``*_COLUMNS``)."""

    classification: pd.DataFrame
    attribution: pd.DataFrame
    dynamics: pd.DataFrame
    timecourses: pd.DataFrame
    variables: Variables | None = None  # layout of the variables (values of one recording)
    settings: Mapping[str, object] = field(default_factory=dict)


def make_svm(C: float, max_iter: int = 10000):  # noqa: ANN201 - sklearn Pipeline
    """StandardScaler + LinearSVC(C, class_weight="balanced"), seeded: liblinear's dual solver
    (used when there are more variables than frames) visits the frames in a random order."""
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler
    from sklearn.svm import LinearSVC

    return make_pipeline(
        StandardScaler(),
        LinearSVC(C=C, class_weight="balanced", dual="auto", max_iter=max_iter, random_state=0),
    )


def is_informative(mean: np.ndarray, std: np.ndarray, rtol: float) -> np.ndarray:
    """True where a column with this mean and standard deviation varies beyond numerical
    noise: ``std > rtol * sqrt(mean² + std²)`` (False for constant and all-NaN columns)."""
    mean = np.asarray(mean, dtype=np.float64)
    std = np.asarray(std, dtype=np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        rms = np.sqrt(mean**2 + std**2)
        return np.isfinite(std) & np.isfinite(rms) & (std > rtol * rms)


def informative_columns(x: np.ndarray, rtol: float = 1e-5) -> np.ndarray:
    """Columns of ``x`` that can be standardized: at least two finite values whose standard
    deviation exceeds ``rtol`` times their root mean square.

    A column below that is constant up to float round-off (e.g. the distance of a rigidly
    attached keypoint to the local origin); ``StandardScaler`` would divide by the round-off
    and turn any offset of that column between recordings into z-scores of ~1e6.

    Args:
        x: (N, V) values (NaN allowed).

    Returns:
        (V,) bool.
    """
    x = np.asarray(x, dtype=np.float64)
    n = np.isfinite(x).sum(axis=0)
    mean = np.zeros(x.shape[1])
    std = np.zeros(x.shape[1])
    ok = n >= 2
    if ok.any():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            mean[ok] = np.nanmean(x[:, ok], axis=0)
            std[ok] = np.nanstd(x[:, ok], axis=0)
    return ok & is_informative(mean, std, rtol)


def confusion(y_true: np.ndarray, y_pred: np.ndarray) -> np.ndarray:
    """2x2 table of counts: rows = true class (0, 1), columns = predicted class."""
    idx = 2 * np.asarray(y_true, dtype=np.int64) + np.asarray(y_pred, dtype=np.int64)
    return np.bincount(idx, minlength=4)[:4].reshape(2, 2).astype(float)


def chi2_pvalue(table: np.ndarray, n_effective: float | None = None) -> float:
    """p-value of ``scipy.stats.chi2_contingency`` on a 2x2 table of true vs. predicted
    classes; 1 when a row or column is empty (a classifier that always predicts one class
    shows no association).

    Args:
        table: (2, 2) counts.
        n_effective: when given, the table is scaled to this many frames first (the
            effective number of independent frames, see :func:`effective_frames`).
    """
    from scipy.stats import chi2_contingency

    table = np.asarray(table, dtype=float)
    n = table.sum()
    if n == 0 or (table.sum(axis=0) == 0).any() or (table.sum(axis=1) == 0).any():
        return 1.0
    if n_effective is not None:
        table = table * (min(n_effective, n) / n)
    return float(chi2_contingency(table).pvalue)


def table_scores(table: np.ndarray) -> tuple[float, float]:
    """(balanced accuracy, macro F1) from a 2x2 true-by-predicted table."""
    (tn, fp), (fn, tp) = np.asarray(table, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        recalls = [tn / (tn + fp) if tn + fp else np.nan, tp / (tp + fn) if tp + fn else np.nan]
        ba = float(np.nanmean(recalls)) if not np.isnan(recalls).all() else float("nan")
    f_pos = 2 * tp / (2 * tp + fp + fn) if (2 * tp + fp + fn) else 0.0
    f_neg = 2 * tn / (2 * tn + fp + fn) if (2 * tn + fp + fn) else 0.0
    return ba, float((f_pos + f_neg) / 2)


def _autocorr(x: np.ndarray, max_lag: int) -> np.ndarray:
    """Autocorrelation at lags 1..max_lag of a 1-D series (FFT; biased estimator)."""
    x = np.asarray(x, dtype=float) - np.mean(x)
    n = len(x)
    var = float(x @ x)
    if var <= 0 or max_lag < 1:
        return np.zeros(max(max_lag, 0))
    size = 1 << int(np.ceil(np.log2(2 * n)))
    f = np.fft.rfft(x, size)
    ac = np.fft.irfft(f * np.conj(f), size)[1 : max_lag + 1]
    return ac / var


def effective_frames(
    y_true: np.ndarray, y_pred: np.ndarray, segments: np.ndarray, max_lag_fraction: float = 0.2
) -> float:
    """Effective number of independent frames for a test of association between two
    autocorrelated series (Bartlett 1935; Pyper & Peterman 1998):
    ``n / (1 + 2 Σ_k ρ_true(k) ρ_pred(k))`` per recording, lags up to a fifth of its length,
    summed over recordings.

    Consecutive video frames are far from independent (and the STFT variables are smooth over
    a whole window), so a chi-squared test that counts every frame as independent declares
    unrelated variables significant; this is the correction.

    Args:
        y_true, y_pred: (N,) labels and predictions in time order, recordings concatenated.
        segments: lengths of the recordings' parts (sum N).
    """
    total = 0.0
    a = 0
    for n in np.asarray(segments, dtype=int):
        yt, yp = y_true[a : a + n], y_pred[a : a + n]
        a += n
        if n < 3:
            total += n
            continue
        lag = max(1, int(n * max_lag_fraction))
        deff = 1.0 + 2.0 * float(_autocorr(yt, lag) @ _autocorr(yp, lag))
        total += n / min(max(deff, 1.0), n)
    return total


def scores(
    y_true: np.ndarray, y_pred: np.ndarray, segments: np.ndarray | None = None
) -> tuple[float, float, float, float, float]:
    """Scores of binary predictions in time order.

    Returns:
        balanced accuracy, macro F1, chi-squared p with every frame counted as independent
        (the method's test), effective number of frames, chi-squared p on that number.
    """
    y_true = np.asarray(y_true).astype(np.int64)
    y_pred = np.asarray(y_pred).astype(np.int64)
    if len(y_true) == 0:
        nan = float("nan")
        return nan, nan, 1.0, 0.0, 1.0
    table = confusion(y_true, y_pred)
    ba, f1 = table_scores(table)
    seg = np.array([len(y_true)]) if segments is None else segments
    n_eff = effective_frames(y_true, y_pred, seg)
    return ba, f1, chi2_pvalue(table), n_eff, chi2_pvalue(table, n_eff)


def label_recordings(
    study: Study, variables: Mapping[str, Variables], config: AttributionConfig
) -> dict[str, LabelledRecording]:
    """Read the events of every recording, check them and label the frames."""
    names = None
    fps = None
    out = {}
    for rec in study.recordings:
        var = variables[rec.name]
        if names is None:
            names, fps, first = var.names, var.fps, rec.name
        elif var.names != names:
            raise StudyError(
                f"recordings {first!r} and {rec.name!r} have different variables (different "
                f"skeletons, STFT settings or frame rates: {fps} vs {var.fps} fps); all "
                f"recordings of a study must give the same variables"
            )
        win = read_events(rec.events)
        check_windows(win, var.num_frames / var.fps, f"events file {rec.events} ({rec.name})")
        labels = label_frames(var.times, win, config.onset_delay_s, config.margin_s)
        out[rec.name] = LabelledRecording(rec, var, win, labels)
    return out


def standardize_recording(values: np.ndarray, rtol: float = 1e-5) -> np.ndarray:
    """Z-score every column of one recording with its own mean and deviation (NaN ignored);
    columns constant up to round-off (:func:`is_informative`) become 0.

    Args:
        values: (T, V) variables of one recording.

    Returns:
        (T, V) float64.
    """
    x = np.asarray(values, dtype=np.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = np.nanmean(x, axis=0)
        std = np.nanstd(x, axis=0)
    ok = is_informative(mean, std, rtol)
    z = (x - np.where(ok, mean, 0.0)) / np.where(ok, std, 1.0)
    return np.where(ok, z, np.where(np.isfinite(x), 0.0, np.nan))


def _stack(
    recs: list[LabelledRecording], stride: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Labelled frames of several recordings: values (N, V), labels (N,), recording (N,)."""
    xs, ys, ids = [], [], []
    for i, r in enumerate(recs):
        keep = np.flatnonzero(r.labels != IGNORED)[::stride]
        xs.append(r.variables.values[keep])
        ys.append(r.labels[keep])
        ids.append(np.full(len(keep), i, dtype=np.int64))
    return np.concatenate(xs), np.concatenate(ys).astype(np.int8), np.concatenate(ids)


def _fit_block(
    xtr: np.ndarray,
    ytr: np.ndarray,
    xte: np.ndarray,
    yte: np.ndarray,
    rec_te: np.ndarray,
    C: float,
    max_iter: int,
    constant_rtol: float = 1e-5,
) -> list[tuple[float, ...]]:
    """Single-variable SVMs on the columns of a block.

    Each column is standardized with its train mean and deviation (as ``StandardScaler``)
    and fitted with ``LinearSVC(C, class_weight="balanced")``; frames where the column is
    NaN are left out. A column that is constant over the train frames up to numerical noise
    (:func:`is_informative` with ``constant_rtol``) is not tested (F1 NaN, p 1).

    Returns:
        per column (F1, p, balanced accuracy, n test frames, n effective, naive p).
    """
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.svm import LinearSVC

    out: list[tuple[float, ...]] = []
    nan = float("nan")
    for j in range(xtr.shape[1]):
        ftr = np.isfinite(xtr[:, j])
        fte = np.isfinite(xte[:, j])
        y_tr, y_te = ytr[ftr], yte[fte]
        if len(np.unique(y_tr)) < 2 or len(y_te) == 0:
            out.append((nan, 1.0, nan, float(len(y_te)), 0.0, 1.0))
            continue
        x = xtr[ftr, j].astype(np.float64)
        mu, sd = x.mean(), x.std()
        if not is_informative(mu, sd, constant_rtol):
            out.append((nan, 1.0, nan, float(len(y_te)), 0.0, 1.0))
            continue
        svm = LinearSVC(C=C, class_weight="balanced", dual=False, max_iter=max_iter)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            svm.fit(((x - mu) / sd)[:, None], y_tr)
        z = (xte[fte, j].astype(np.float64) - mu) / sd
        pred = (z * svm.coef_[0, 0] + svm.intercept_[0] > 0).astype(np.int64)
        seg = np.bincount(rec_te[fte])
        ba, f1, p_naive, n_eff, p_eff = scores(y_te, pred, seg[seg > 0])
        out.append((f1, p_eff, ba, float(len(y_te)), n_eff, p_naive))
    return out


def single_variable_scores(
    xtr: np.ndarray,
    ytr: np.ndarray,
    xte: np.ndarray,
    yte: np.ndarray,
    rec_te: np.ndarray,
    config: AttributionConfig,
    desc: str = "single-variable SVMs",
) -> np.ndarray:
    """Fit one SVM per column in parallel (joblib) with a progress bar.

    Args:
        xtr: (N, V) train values; ytr (N,) labels in {0, 1}.
        xte: (M, V) test values in time order; yte (M,) labels.
        rec_te: (M,) index of the test recording of each test frame.

    Returns:
        (V, 6) float: macro F1, chi-squared p (effective frames), balanced accuracy, number
        of test frames, effective number of frames, chi-squared p (frames independent).
    """
    from joblib import Parallel, delayed
    from tqdm import tqdm

    v = xtr.shape[1]
    blocks = [(a, min(v, a + config.block)) for a in range(0, v, config.block)]
    jobs = (
        delayed(_fit_block)(
            xtr[:, a:b],
            ytr,
            xte[:, a:b],
            yte,
            rec_te,
            config.C,
            config.max_iter,
            config.constant_rtol,
        )
        for a, b in blocks
    )
    res: list[tuple[float, ...]] = []
    with tqdm(total=v, desc=desc, unit="var", disable=None, leave=False) as bar:
        par = Parallel(n_jobs=config.n_jobs, return_as="generator")
        for block in par(jobs):
            res.extend(block)
            bar.update(len(block))
    return np.array(res, dtype=float).reshape(v, 6)


def onset_aligned(
    signal: np.ndarray, windows: np.ndarray, fps: float, pre_s: float, span_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Cut a per-frame signal into trials aligned to stimulation onsets.

    Args:
        signal: (T,) or (T, D) per-frame values (NaN allowed).
        windows: (N, 2) seconds from the first frame.
        pre_s: seconds before onset; span_s: seconds after onset.

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


def _mean_sem(trials: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = np.isfinite(trials).sum(axis=0)
    with warnings.catch_warnings(), np.errstate(invalid="ignore", divide="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = np.nanmean(trials, axis=0)
        sd = np.nanstd(trials, axis=0, ddof=1)
    sem = np.where(n > 1, sd / np.sqrt(np.maximum(n, 1)), np.nan)
    return mean, sem, n


def _predict_frames(model, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # noqa: ANN001
    """Per-frame decision value and predicted class (NaN where a variable is NaN)."""
    ok = np.isfinite(values).all(axis=1)
    dec = np.full(len(values), np.nan)
    if ok.any():
        dec[ok] = model.decision_function(values[ok])
    pred = np.where(ok, (dec > 0).astype(float), np.nan)
    return dec, pred


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

    Returns:
        The four result tables.
    """
    say = log_fn or log.info
    recs = label_recordings(study, variables, config)
    if config.standardize == "recording":
        recs = {
            name: dataclasses.replace(
                r,
                variables=dataclasses.replace(
                    r.variables,
                    values=standardize_recording(r.variables.values, config.constant_rtol),
                ),
            )
            for name, r in recs.items()
        }
    first = next(iter(recs.values())).variables
    fps = first.fps
    names = first.names
    keypoint_lists = [";".join(first.involved_names(i)) for i in range(len(names))]
    types = first.types
    max_len = max(
        (float(np.max(r.windows[:, 1] - r.windows[:, 0])) for r in recs.values() if len(r.windows)),
        default=0.0,
    )
    span = max_len + config.post_s
    cls_rows, att_frames, dyn_rows, tc_rows = [], [], [], []
    n_groups = len(study.groups)
    for gi, (animal, cond) in enumerate(study.groups, start=1):
        train = [recs[r.name] for r in study.select(animal, cond, "train")]
        xtr_all, ytr_all, _ = _stack(train, config.train_stride)
        # Columns constant up to round-off (or undefined) in the train frames carry no
        # information and would blow up under standardization: left out of the full SVM.
        cols = np.flatnonzero(informative_columns(xtr_all, config.constant_rtol))
        if len(cols) == 0:
            raise StudyError(
                f"group (animal {animal!r}, condition {cond!r}): no variable varies over the "
                f"train frames (all {len(names)} are constant or undefined); check the poses "
                f"of the train recordings"
            )
        fin = np.isfinite(xtr_all[:, cols]).all(axis=1)
        xtr, ytr = xtr_all[fin][:, cols], ytr_all[fin]
        n_nan = int((~fin).sum())
        counts = np.bincount(ytr, minlength=2)
        if counts.min() == 0:
            raise StudyError(
                f"group (animal {animal!r}, condition {cond!r}): the train recordings have "
                f"{counts[1]} stimulated and {counts[0]} not-stimulated usable frames; both are "
                f"needed (check the events files, --onset-delay and --margin, and missing poses)"
            )
        say(
            f"[{gi}/{n_groups}] {animal} / {cond}: training on {len(ytr)} frames "
            f"({counts[1]} stimulated; {n_nan} with undefined variables left out) on "
            f"{len(cols)} of {len(names)} variables ({len(names) - len(cols)} constant or "
            f"undefined over the train frames left out)"
        )
        from sklearn.exceptions import ConvergenceWarning

        model = make_svm(config.C, config.max_iter)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            model.fit(xtr, ytr)
        # Full classifier on the group's own test recordings and other animals' (same condition).
        targets = [animal] + sorted(
            {r.animal for r in study.recordings if r.condition == cond and r.split == "test"}
            - {animal}
        )
        for target in targets:
            tests = [recs[r.name] for r in study.select(target, cond, "test")]
            ys, ps, segs, trials_p, trials_d, stim_masks = [], [], [], [], [], []
            for r in tests:
                dec, pred = _predict_frames(model, r.variables.values[:, cols])
                m = (r.labels != IGNORED) & np.isfinite(pred)
                ys.append(r.labels[m])
                ps.append(pred[m])
                segs.append(int(m.sum()))
                if len(r.windows):
                    t_rel, tp = onset_aligned(pred, r.windows, fps, config.pre_s, span)
                    _, td = onset_aligned(dec, r.windows, fps, config.pre_s, span)
                    trials_p.append(tp)
                    trials_d.append(td)
                    dur = r.windows[:, 1] - r.windows[:, 0]
                    stim_masks.append((t_rel[None, :] >= 0) & (t_rel[None, :] <= dur[:, None]))
            y, p = np.concatenate(ys).astype(int), np.concatenate(ps).astype(int)
            ba, f1, pv_naive, n_eff, pv = scores(y, p, np.array(segs))
            if config.independent_frames:
                pv = pv_naive
            cls_rows.append(
                {
                    "animal": animal,
                    "condition": cond,
                    "evaluated_on": target,
                    "balanced_accuracy": ba,
                    "f1": f1,
                    "n_frames": int(len(y)),
                    "n_stimulated": int(y.sum()),
                    "p_value": pv,
                    "n_effective": n_eff,
                    "n_train_frames": int(len(ytr)),
                    "n_train_nan_excluded": n_nan,
                    "n_variables_used": int(len(cols)),
                }
            )
            say(
                f"    evaluated on {target}: balanced accuracy {ba:.3f}, F1 {f1:.3f}, "
                f"{len(y)} frames"
            )
            if trials_p:
                tp_all, td_all = np.concatenate(trials_p), np.concatenate(trials_d)
                mp, sp, n = _mean_sem(tp_all)
                md, _, _ = _mean_sem(td_all)
                sf = np.concatenate(stim_masks).mean(axis=0)
                for j, tt in enumerate(t_rel):
                    dyn_rows.append(
                        {
                            "animal": animal,
                            "condition": cond,
                            "evaluated_on": target,
                            "time_s": round(float(tt), 6),
                            "mean_prediction": mp[j],
                            "sem_prediction": sp[j],
                            "mean_decision": md[j],
                            "n_trials": int(n[j]),
                            "stimulated_fraction": float(sf[j]),
                        }
                    )
        # Single-variable SVMs on the group's own test recordings.
        own = [recs[r.name] for r in study.select(animal, cond, "test")]
        xte, yte, rte = _stack(own)
        res = single_variable_scores(
            xtr_all, ytr_all, xte, yte, rte, config, desc=f"{animal}/{cond} single-variable SVMs"
        )
        f1s, pvals, bas, nte, neff, pnaive = res.T
        if config.independent_frames:
            pvals = pnaive
        n_tested = int(np.isfinite(f1s).sum())
        padj = np.minimum(1.0, pvals * max(n_tested, 1))
        sig = (padj < config.alpha) & (bas > 0.5)
        df = pd.DataFrame(
            {
                "animal": animal,
                "condition": cond,
                "variable": names,
                "keypoints": keypoint_lists,
                "f1": f1s,
                "p_value": pvals,
                "p_adjusted": padj,
                "significant": sig,
                "balanced_accuracy": bas,
                "type": types,
                "part": first.parts,
                "n_frames": nte.astype(int),
                "n_effective": neff,
                "p_value_independent": pnaive,
            }
        )
        df = df.sort_values(
            ["f1", "p_value"], ascending=[False, True], na_position="last", kind="stable"
        )
        df.insert(2, "rank", np.arange(1, len(df) + 1))
        att_frames.append(df[ATTRIBUTION_COLUMNS])
        say(
            f"    single variables: {int(sig.sum())} of {len(names)} significant "
            f"(p_adjusted < {config.alpha}); best {df['variable'].iloc[0]} "
            f"F1 {df['f1'].iloc[0]:.3f}"
        )
        # Time courses of the top variables (z-scored with train statistics) around onset.
        mu = np.nanmean(xtr_all, axis=0)
        sd = np.nanstd(xtr_all, axis=0)
        sd = np.where(sd > 0, sd, 1.0)
        top = df.head(config.top)
        cols = [names.index(v) for v in top["variable"]]
        trials = [
            onset_aligned(
                (r.variables.values[:, cols] - mu[cols]) / sd[cols],
                r.windows,
                fps,
                config.pre_s,
                span,
            )
            for r in own
            if len(r.windows)
        ]
        if trials:
            t_rel = trials[0][0]
            allt = np.concatenate([tr for _, tr in trials])  # (N, L, D)
            for d, (vname, rank) in enumerate(zip(top["variable"], top["rank"])):
                m, s, n = _mean_sem(allt[:, :, d])
                for j, tt in enumerate(t_rel):
                    tc_rows.append(
                        {
                            "animal": animal,
                            "condition": cond,
                            "variable": vname,
                            "rank": int(rank),
                            "time_s": round(float(tt), 6),
                            "mean_z": m[j],
                            "sem_z": s[j],
                            "n_trials": int(n[j]),
                        }
                    )
    return AttributionResult(
        classification=pd.DataFrame(cls_rows, columns=CLASSIFICATION_COLUMNS),
        attribution=pd.concat(att_frames, ignore_index=True),
        dynamics=pd.DataFrame(dyn_rows, columns=DYNAMICS_COLUMNS),
        timecourses=pd.DataFrame(tc_rows, columns=TIMECOURSE_COLUMNS),
        variables=first,
        settings={k: getattr(config, k) for k in config.__dataclass_fields__},
    )
