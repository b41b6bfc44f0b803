"""Single-variable SVMs.

One linear SVM per variable, trained on a group's train frames and
scored on its test frames (macro F1 and a chi-squared test of predicted vs. true classes,
Bonferroni-corrected over the tested variables), ranked into ``attribution.csv``.

A variable is *significant* when its adjusted p-value is below ``alpha`` and it does better
than chance (balanced accuracy > 0.5); a classifier that is reliably wrong is not an effect
of the stimulation on that variable.
"""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd

from freipose.analysis.config import AttributionConfig
from freipose.analysis.stats import is_informative, scores
from freipose.analysis.variables import Variables

ATTRIBUTION_COLUMNS = (
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
)


def fit_block(
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
    (:func:`~freipose.analysis.stats.is_informative` with ``constant_rtol``) is not tested
    (F1 NaN, p 1); a column without a defined test frame gets no p-value (all NaN).

    Args:
        xtr: (N, B) train values.
        ytr: (N,) train labels in {0, 1}.
        xte: (M, B) test values in time order.
        yte: (M,) test labels.
        rec_te: (M,) index of the test recording of each test frame.
        C: SVM regularization.
        max_iter: LinearSVC iteration limit.
        constant_rtol: see :func:`~freipose.analysis.stats.is_informative`.

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
        if len(y_te) == 0:  # no test frame: no test, no p-value
            out.append((nan, nan, nan, 0.0, 0.0, nan))
            continue
        if len(np.unique(y_tr)) < 2:
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
        xtr: (N, V) train values.
        ytr: (N,) train labels in {0, 1}.
        xte: (M, V) test values in time order.
        yte: (M,) test labels.
        rec_te: (M,) index of the test recording of each test frame.
        config: C, iteration limit, constant threshold, block size and workers.
        desc: progress bar text.

    Returns:
        (V, 6) float: macro F1, chi-squared p (effective frames), balanced accuracy, number
        of test frames, effective number of frames, chi-squared p (frames independent).
    """
    from joblib import Parallel, delayed

    from freipose.progress import progress_bar

    v = xtr.shape[1]
    blocks = [(a, min(v, a + config.block)) for a in range(0, v, config.block)]
    jobs = (
        delayed(fit_block)(
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
    with progress_bar(total=v, desc=desc, unit="var", disable=None, leave=False) as bar:
        par = Parallel(n_jobs=config.n_jobs, return_as="generator")
        for block in par(jobs):
            res.extend(block)
            bar.update(len(block))
    return np.array(res, dtype=float).reshape(v, 6)


def attribution_table(
    animal: str,
    condition: str,
    res: np.ndarray,
    layout: Variables,
    config: AttributionConfig,
) -> pd.DataFrame:
    """Rank a group's variables by their single-variable scores.

    Args:
        animal: the group's animal.
        condition: the group's condition.
        res: (V, 6) scores from :func:`single_variable_scores`.
        layout: variables with the names, keypoints, types and parts of the V columns.
        config: significance level and test.

    Returns:
        The group's ``attribution.csv`` rows (columns :data:`ATTRIBUTION_COLUMNS`), best first.
    """
    names = layout.names
    f1s, pvals, bas, nte, neff, pnaive = res.T
    if config.independent_frames:
        pvals = pnaive
    n_tested = int(np.isfinite(f1s).sum())
    padj = np.minimum(1.0, pvals * max(n_tested, 1))
    sig = (padj < config.alpha) & (bas > 0.5)
    df = pd.DataFrame(
        {
            "animal": animal,
            "condition": condition,
            "variable": names,
            "keypoints": [";".join(layout.involved_names(i)) for i in range(len(names))],
            "f1": f1s,
            "p_value": pvals,
            "p_adjusted": padj,
            "significant": sig,
            "balanced_accuracy": bas,
            "type": layout.types,
            "part": layout.parts,
            "n_frames": nte.astype(int),
            "n_effective": neff,
            "p_value_independent": pnaive,
        }
    )
    df = df.sort_values(
        ["f1", "p_value"], ascending=[False, True], na_position="last", kind="stable"
    )
    df.insert(2, "rank", np.arange(1, len(df) + 1))
    return df[list(ATTRIBUTION_COLUMNS)]
