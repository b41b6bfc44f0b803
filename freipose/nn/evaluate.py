"""Accuracy of trained networks on labeled data: joint position error (JPE) and PCK.

JPE (eq. 5.5 of the method) is the Euclidean distance in mm between a predicted keypoint and
its 3D label, over every labeled keypoint of every evaluated time instant. The cube centre
of each sample is the mean of its labeled 3D points (the detector is evaluated separately),
optionally displaced by Gaussian noise to mimic detector error.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np

from freipose.errors import FreiPoseError
from freipose.geometry.crops import label_centers
from freipose.io.atomic import atomic_write_text
from freipose.io.figures import new_figure, save_figure
from freipose.io.labels import read_labels_h5
from freipose.nn.checkpoint import load_checkpoint
from freipose.nn.compare import PairedDifference, paired_difference
from freipose.nn.config import InferenceOverrides, TrainConfig
from freipose.nn.data import collate_prepared, prepare_sample
from freipose.nn.dataset import MultiViewDataset, other_rows
from freipose.nn.failure_modes import NOT_LABELED
from freipose.nn.fast import optimize
from freipose.nn.inference import predict_prepared
from freipose.nn.types import Sample, SampleSource
from freipose.progress import progress_bar
from freipose.skeleton import Skeleton

log = logging.getLogger(__name__)

PCK_THRESHOLDS = np.linspace(0.0, 20.0, 41)


class EvaluationError(FreiPoseError):
    """A network cannot be evaluated on the given labels (the message says why)."""


def usable_indices(source: SampleSource) -> np.ndarray:
    """Indices of samples with at least one 3D label.

    Args:
        source: a :class:`~freipose.nn.dataset.MultiViewDataset` (its labels are read, and
            sessions without a calibration skipped) or any sequence of samples (read one by one).

    Returns:
        (N,) int64 indices.
    """
    labels = getattr(source, "labels", None)
    if labels is not None:
        p3 = labels.points3d
        ok = np.isfinite(p3).all(-1).any(-1)
        views = getattr(source, "_views", None)
        if views is not None:
            ok &= np.array([views[str(s)][2] is not None for s in labels.session], bool)
        return np.flatnonzero(ok)
    return np.array(
        [
            i
            for i in range(len(source))
            if np.isfinite(np.asarray(source[i]["points3d"])).all(-1).any()
        ],
        dtype=np.int64,
    )


def first_pass_sample(sample: Sample) -> Sample:
    """The sample as a first inference pass sees it: without the other animals' labels.

    ``others3d`` of a labels file are the true poses of the other animals; inference knows
    them only from its own earlier pass (:func:`_painted_pass`), so evaluation must not use
    them.
    """
    if "others3d" not in sample:
        return sample
    out = dict(sample)
    out.pop("others3d")
    return cast(Sample, out)


def _painted_pass(
    model: Any,
    source: SampleSource,
    idx: np.ndarray,
    centres: Sequence[np.ndarray],
    moments: Sequence[tuple[str, int]],
    prev: np.ndarray,
    batch_size: int,
) -> dict[str, np.ndarray]:
    """``model.mask_others``: predict again with the other animals painted out.

    Each sample's own pose and those of the other animals at its instant (same session and
    frame) are the previous pass's P1 (``prev``, (N, K, 3)).

    Returns:
        ``P0``, ``P1`` (N, K, 3) and ``confidence`` (N, K).
    """
    others_of = other_rows(moments)
    outs: dict[str, list[np.ndarray]] = {"P0": [], "P1": [], "confidence": []}
    for start in range(0, len(idx), batch_size):
        items = []
        for r in range(start, min(start + batch_size, len(idx))):
            s = dict(first_pass_sample(source[int(idx[r])]))
            s["own3d"] = prev[r]
            s["others3d"] = prev[others_of[r]]
            items.append(prepare_sample(cast(Sample, s), model.cfg, center=centres[r]))
        pred = predict_prepared(model, collate_prepared(items))
        for k in outs:
            outs[k].append(pred[k])
    return {k: np.concatenate(v) for k, v in outs.items()}


def predict_dataset(
    model: Any,
    source: SampleSource,
    indices: Sequence[int] | np.ndarray | None = None,
    batch_size: int = 4,
    center_noise: float = 0.0,
    seed: int = 0,
    progress: bool = False,
) -> dict[str, np.ndarray]:
    """Predict every (usable) sample of ``source`` with the cube on its label centre.

    Args:
        model: a network from :func:`freipose.nn.checkpoint.load_checkpoint`.
        source: labeled samples.
        indices: the samples to predict (default: :func:`usable_indices`).
        batch_size: samples per forward pass.
        center_noise: std (mm) of Gaussian noise added to each cube centre.
        seed: seed of that noise.
        progress: show a progress bar.

    Returns:
        ``P0``, ``P1`` (N, K, 3), ``confidence`` (N, K), ``gt`` (N, K, 3) (NaN unknown) and
        ``index`` (N,).
    """
    cfg = model.cfg
    idx = usable_indices(source) if indices is None else np.asarray(indices, dtype=np.int64)
    rng = np.random.default_rng(seed)
    centres: list[np.ndarray] = []
    outs: dict[str, list[np.ndarray]] = {"P0": [], "P1": [], "confidence": [], "gt": []}
    moments: list[tuple[str, int]] = []
    model.eval()
    for start in progress_bar(
        range(0, len(idx), batch_size), desc="evaluate", disable=not progress or None
    ):
        items = []
        for i in idx[start : start + batch_size]:
            s = first_pass_sample(source[int(i)])
            c = label_centers(s["points3d"], s.get("mask3d"))
            if center_noise > 0:
                c = c + rng.normal(0, center_noise, size=3)
            centres.append(c)
            moments.append((str(s.get("session", "")), int(s.get("frame_index", -1))))
            items.append(prepare_sample(s, cfg, center=c))
            gt = np.asarray(s["points3d"], np.float64).copy()
            if s.get("mask3d") is not None:
                gt[~np.asarray(s["mask3d"], bool)] = np.nan
            outs["gt"].append(gt[None])
        pred = predict_prepared(model, collate_prepared(items))
        for k in ("P0", "P1", "confidence"):
            outs[k].append(pred[k])
    if getattr(cfg, "mask_others", False) and len(idx):
        for _ in range(cfg.mask_passes):
            prev = np.concatenate(outs["P1"])
            painted = _painted_pass(model, source, idx, centres, moments, prev, batch_size)
            outs.update({k: [v] for k, v in painted.items()})
    res = {k: np.concatenate(v) if v else np.zeros((0,)) for k, v in outs.items()}
    res["index"] = idx
    return res


@dataclass(frozen=True, eq=False)
class Evaluation:
    """Networks' predictions of labeled instants and their errors (``freipose eval``).

    Attributes:
        errors: result name -> (N, K) JPE in mm (a voxel network gives ``<name>_P0`` and
            ``<name>_P1``, a baseline ``<name>``).
        predictions: result name -> (N, K, 3) predicted keypoints (mm).
        gt: (N, K, 3) the labels (mm), NaN where unknown.
        skeleton: the networks' skeleton (its keypoints are the labels').
        checkpoints: result name -> the checkpoint it came from.
        configs: result name -> the training config of that checkpoint.
        settings: result name -> :func:`settings_report` of its checkpoint.
    """

    errors: dict[str, np.ndarray]
    predictions: dict[str, np.ndarray]
    gt: np.ndarray
    skeleton: Skeleton
    checkpoints: dict[str, Path]
    configs: dict[str, TrainConfig]
    settings: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)

    @property
    def keypoints(self) -> tuple[str, ...]:
        """The K keypoint names."""
        return tuple(self.skeleton.keypoints)


def evaluate_checkpoints(
    checkpoints: Mapping[str, str | Path],
    labels: str | Path,
    *,
    root: str | Path | None = None,
    device: str = "cpu",
    batch_size: int = 4,
    center_noise: float = 0.0,
    progress: bool = False,
    overrides: InferenceOverrides | None = None,
) -> Evaluation:
    """Joint position errors of trained networks on a labels file (``freipose eval``).

    Args:
        checkpoints: method name -> checkpoint; an empty name is replaced by the network's
            kind (``voxel`` or ``baseline``).
        labels: the ``labels.h5`` file with 3D labels.
        root: the folder the videos are relative to (default: the labels file's folder).
        device: where the networks run.
        batch_size: samples per forward pass.
        center_noise: std (mm) of Gaussian noise added to each cube centre.
        progress: show progress bars.
        overrides: inference-only ``[model]`` settings of every network instead of their
            checkpoints' (``--fusion-reject``, ``--map-window``; None: their own).

    Returns:
        The predictions and errors of every network.

    Raises:
        EvaluationError: a network predicts other keypoints than the labels have, or no
            labeled instant has 3D labels and a calibration.
    """
    labels = Path(labels)
    lab = read_labels_h5(labels)
    ds = MultiViewDataset(lab, root=Path(root) if root else labels.resolve().parent)
    errors: dict[str, np.ndarray] = {}
    preds: dict[str, np.ndarray] = {}
    paths: dict[str, Path] = {}
    configs: dict[str, TrainConfig] = {}
    gt = np.zeros((0, len(lab.keypoints), 3))
    skel = Skeleton(name="labels", keypoints=tuple(lab.keypoints))
    for name, path in checkpoints.items():
        model, config, skeleton = load_checkpoint(path, device, overrides=overrides)
        optimize(model, "optimized")  # the eager poses within fp32 rounding (nn.fast)
        if tuple(skeleton.keypoints) != tuple(lab.keypoints):
            raise EvaluationError(
                f"{path}: the network predicts keypoints {list(skeleton.keypoints)} but "
                f"{labels} has {list(lab.keypoints)}"
            )
        skel = skeleton if not (skel.limbs or skel.symmetry) else skel
        pred = predict_dataset(
            model, ds, batch_size=batch_size, center_noise=center_noise, progress=progress
        )
        if len(pred["index"]) == 0:
            raise EvaluationError(f"{labels}: no labeled instant with 3D labels and a calibration")
        gt = pred["gt"]
        label = name or ("voxel" if config.model.kind == "voxel" else "baseline")
        outs = ("P0", "P1") if config.model.kind == "voxel" else ("P1",)
        for out in outs:
            key = f"{label}_{out}" if len(outs) == 2 else label
            errors[key], preds[key] = jpe(pred[out], gt), pred[out]
            paths[key], configs[key] = Path(path), config
    settings = {k: settings_report(paths[k], configs[k]) for k in paths}
    return Evaluation(errors, preds, gt, skel, paths, configs, settings)


def settings_report(path: Path, config: TrainConfig) -> dict[str, Any]:
    """The inference settings a network was evaluated with, and where they come from.

    Args:
        path: the checkpoint.
        config: its config as evaluated (with any ``--map-window``/``--fusion-reject``).

    Returns:
        ``used`` (the settings that acted), and for a checkpoint whose settings were chosen
        on validation labels after training (:mod:`freipose.nn.validation`) ``validation``:
        its ``chosen`` and ``configured`` values, the validation ``instants``, the median
        P1 error (mm) of every value ``tried`` and the ``uncertainty_scale``.
    """
    from freipose.nn.checkpoint import validation_record
    from freipose.nn.config import inference_settings

    out: dict[str, Any] = {"used": inference_settings(config.model)}
    record = validation_record(path)
    if record:
        out["validation"] = record
    return out


def trained_on(evaluation: Evaluation) -> tuple[Path | None, str]:
    """The training labels the evaluated networks' checkpoints record, if they exist.

    The first checkpoint whose config's ``[data] labels`` names an existing file wins: an
    absolute path as recorded, a relative one (older checkpoints) next to the checkpoint
    or in the folder above it (a run folder beside its config file).

    Args:
        evaluation: what :func:`evaluate_checkpoints` returned.

    Returns:
        ``(path, why)``: the labels file, or None, and a phrase saying where it came from
        (or why none was found).
    """
    tried = []
    for name, cfg in evaluation.configs.items():
        rec = cfg.data.labels
        if not rec:
            continue
        ckpt = evaluation.checkpoints[name]
        q = Path(rec).expanduser()
        for cand in [q] if q.is_absolute() else [ckpt.parent / q, ckpt.parent.parent / q]:
            if cand.is_file():
                return cand, f"the labels {ckpt} was trained on"
            tried.append(str(cand))
    if tried:
        return None, f"the checkpoints' training labels are not found ({', '.join(tried)})"
    return None, "the checkpoints do not record their training labels"


@dataclass(frozen=True)
class Sanity:
    """Failure modes per result and the constant-pose references of an evaluation.

    Attributes:
        failure_modes: result name -> :func:`freipose.nn.failure_modes.failure_modes`.
        references: reference name -> ``{"median_mm", "n"}`` (empty without training labels).
        reference_errors: reference name -> (N, K) JPE in mm.
        warnings: the failure modes' warnings and one per network not beating the
            held-out-centre reference.
        comparisons: every two results of different checkpoints, and every result
            against the held-out-centre reference, on the same instants
            (:func:`freipose.nn.compare.paired_difference`).
    """

    failure_modes: dict[str, dict[str, Any]]
    references: dict[str, dict[str, Any]]
    reference_errors: dict[str, np.ndarray]
    warnings: list[str]
    comparisons: tuple[PairedDifference, ...] = ()


def sanity_checks(evaluation: Evaluation, train3d: np.ndarray | None) -> Sanity:
    """Failure modes of every result and, given training labels, the sanity references.

    Args:
        evaluation: what :func:`evaluate_checkpoints` returned.
        train3d: (M, K, 3) the training labels' 3D points (mm), or None.

    Returns:
        The :class:`Sanity` of the evaluation.
    """
    from freipose.nn.failure_modes import failure_modes
    from freipose.nn.references import (
        beats_reference_warnings,
        reference_predictions,
        reference_summary,
    )

    modes = {
        n: failure_modes(p, evaluation.gt, evaluation.skeleton, n)
        for n, p in evaluation.predictions.items()
    }
    warnings = [w for m in modes.values() for w in m["warnings"]]
    refs: dict[str, dict[str, Any]] = {}
    ref_err: dict[str, np.ndarray] = {}
    if train3d is not None:
        ref_pred = reference_predictions(train3d, evaluation.gt)
        ref_err = {n: jpe(p, evaluation.gt) for n, p in ref_pred.items()}
        refs = reference_summary(ref_err)
        medians = {n: jpe_summary(e, evaluation.keypoints)["overall"]["median"]
                   for n, e in evaluation.errors.items()}  # fmt: skip
        warnings += beats_reference_warnings(medians, refs)
    return Sanity(modes, refs, ref_err, warnings, _comparisons(evaluation, ref_err))


def _comparisons(
    evaluation: Evaluation, reference_errors: Mapping[str, np.ndarray]
) -> tuple[PairedDifference, ...]:
    """Paired differences of the results of different networks, and against the reference."""
    from freipose.nn.references import AT_HELD_OUT

    names = list(evaluation.errors)
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1 :]
             if evaluation.checkpoints[a] != evaluation.checkpoints[b]]  # fmt: skip
    errs = dict(evaluation.errors)
    if AT_HELD_OUT in reference_errors:
        errs[AT_HELD_OUT] = reference_errors[AT_HELD_OUT]
        pairs += [(a, AT_HELD_OUT) for a in names]
    found = (paired_difference(errs[a], errs[b], a, b) for a, b in pairs)
    return tuple(c for c in found if c is not None)


def jpe(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Joint position errors in mm; NaN where the label is unknown.

    A missing prediction (NaN) where a label exists counts as an infinite error (it fails
    every PCK threshold and pushes medians up), so methods that give up are not flattered.

    Args:
        pred: (N, K, 3) predictions (mm), NaN where missing.
        gt: (N, K, 3) labels (mm), NaN where unknown.

    Returns:
        (N, K) errors.
    """
    e = np.linalg.norm(pred - gt, axis=-1)
    labeled = np.isfinite(gt).all(-1)
    e = np.where(labeled & ~np.isfinite(e), np.inf, e)
    return np.where(labeled, e, np.nan)


def jpe_summary(errors: np.ndarray, keypoints: Sequence[str]) -> dict[str, Any]:
    """Median and 30/70 % percentiles overall and per keypoint, and the PCK curve 0-20 mm.

    Args:
        errors: (N, K) joint position errors (mm), NaN where unlabeled, inf where missing.
        keypoints: the K keypoint names.

    Returns:
        ``overall``, ``per_keypoint`` (name -> statistics; a keypoint never labeled has
        None values and ``note``: ``not labeled``) and ``pck``.
    """

    def stats(e: np.ndarray) -> dict[str, float]:
        e = e[~np.isnan(e)]
        if e.size == 0:
            return {"median": float("nan"), "p30": float("nan"), "p70": float("nan"), "n": 0}
        q = np.percentile(np.minimum(e, 1e12), [50, 30, 70])  # inf = missing prediction
        q = np.where(q >= 1e12, np.inf, q)
        return {
            "median": float(q[0]),
            "p30": float(q[1]),
            "p70": float(q[2]),
            "n": int(e.size),
            "missing": int(np.isinf(e).sum()),
        }

    def keypoint_stats(e: np.ndarray) -> dict[str, Any]:  # never labeled: no values, why
        st = stats(e)
        return st if st["n"] else {**dict.fromkeys(("median", "p30", "p70")), "n": 0,
                                   "note": NOT_LABELED}  # fmt: skip

    flat = errors[~np.isnan(errors)]
    pck = [float((flat <= t).mean()) if flat.size else float("nan") for t in PCK_THRESHOLDS]
    return {
        "overall": stats(errors.reshape(-1)),
        "per_keypoint": {k: keypoint_stats(errors[:, i]) for i, k in enumerate(keypoints)},
        "pck": {"thresholds_mm": PCK_THRESHOLDS.tolist(), "fraction": pck},
    }


def _pck_figure(out: Path, summary: Mapping[str, Any]) -> None:
    """``pck.png``: the PCK curves of the methods in ``summary``."""
    fig = new_figure((5, 4))
    ax = fig.subplots()
    for n in summary:
        ax.plot(PCK_THRESHOLDS, summary[n]["pck"]["fraction"], label=n)
    ax.set_xlabel("error threshold (mm)")
    ax.set_ylabel("fraction of keypoints (PCK)")
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    save_figure(fig, out / "pck.png", dpi=120, format="png")


def _boxplot_figure(out: Path, results: Mapping[str, np.ndarray], keypoints: Sequence[str]) -> None:
    """``jpe_boxplot.png``: horizontal box plots of the errors, one row per keypoint."""
    names = list(results)
    fig = new_figure((8, 1.2 + 0.3 * len(keypoints) * max(1, len(names)) ** 0.5))
    ax = fig.subplots()
    height = 0.8 / len(names)
    for j, n in enumerate(names):
        e = results[n]
        data = []
        for i in range(len(keypoints)):
            col = e[:, i]
            col = col[np.isfinite(col)]
            data.append(col if col.size else np.array([np.nan]))
        pos = np.arange(len(keypoints)) + (j - (len(names) - 1) / 2) * height
        bp = ax.boxplot(
            data, positions=pos, widths=height * 0.85, whis=1.5, showfliers=False,
            patch_artist=True, orientation="horizontal", medianprops={"color": "black"},
        )  # fmt: skip
        for patch in bp["boxes"]:
            patch.set_facecolor(f"C{j}")
            patch.set_alpha(0.6)
        ax.plot([], [], color=f"C{j}", lw=6, alpha=0.6, label=n)
    ax.set_yticks(np.arange(len(keypoints)))
    ax.set_yticklabels(keypoints, fontsize=9)
    ax.set_ylim(len(keypoints) - 0.5, -0.5)  # the first keypoint on top
    ax.set_xlabel("joint position error (mm)")
    ax.set_xlim(left=0)
    ax.grid(axis="x", alpha=0.3)
    ax.legend(loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=len(names), fontsize=8)
    fig.tight_layout()
    save_figure(fig, out / "jpe_boxplot.png", dpi=120, format="png")


def write_report(
    out_dir: str | Path,
    results: Mapping[str, np.ndarray],
    keypoints: Sequence[str],
    sanity: Sanity | None = None,
    settings: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Write the evaluation outputs for one or more methods.

    Writes ``metrics.json`` (summaries; with ``sanity`` also each method's
    ``failure_modes`` and a top-level ``references``), ``jpe_per_keypoint.csv``
    (median/p30/p70 per method and keypoint; empty for a keypoint never labeled),
    ``pck.csv`` and ``pck.png`` (PCK 0-20 mm),
    ``jpe_boxplot.png`` (box plots per keypoint, whiskers 1.5 IQR).

    Args:
        out_dir: the output folder (created).
        results: method name -> JPE array (N, K) in mm.
        keypoints: the K keypoint names.
        sanity: the failure modes and references (:func:`sanity_checks`), if computed.
        settings: method name -> :func:`settings_report` (each method's
            ``inference_settings`` in metrics.json), if known.

    Returns:
        The summaries (method name -> :func:`jpe_summary`, plus ``failure_modes``).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary = {name: jpe_summary(e, keypoints) for name, e in results.items()}
    doc: dict[str, Any] = dict(summary)
    if sanity is not None:
        for name, modes in sanity.failure_modes.items():
            if name in summary:
                summary[name]["failure_modes"] = modes
        if sanity.references:
            doc["references"] = sanity.references
        if sanity.comparisons:
            doc["comparisons"] = [c.to_dict() for c in sanity.comparisons]
    for name, rep in (settings or {}).items():
        if name in summary:
            summary[name]["inference_settings"] = rep
    atomic_write_text(out / "metrics.json", json.dumps(doc, indent=2, allow_nan=True) + "\n")
    rows = ["method,keypoint,median_mm,p30_mm,p70_mm,n"]
    for name, s in summary.items():
        for k in [*keypoints, "ALL"]:
            st = s["overall"] if k == "ALL" else s["per_keypoint"][k]
            if not st["n"]:  # never labeled: empty cells, not "nan"
                rows.append(f"{name},{k},,,,0")
                continue
            rows.append(f"{name},{k},{st['median']:.4f},{st['p30']:.4f},{st['p70']:.4f},{st['n']}")
    atomic_write_text(out / "jpe_per_keypoint.csv", "\n".join(rows) + "\n")
    names = list(summary)
    lines = ["threshold_mm," + ",".join(names)]
    for i, t in enumerate(PCK_THRESHOLDS):
        lines.append(
            f"{t:.2f}," + ",".join(f"{summary[n]['pck']['fraction'][i]:.5f}" for n in names)
        )
    atomic_write_text(out / "pck.csv", "\n".join(lines) + "\n")
    _pck_figure(out, summary)
    _boxplot_figure(out, results, keypoints)
    return summary
