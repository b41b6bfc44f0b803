"""Step 6, ``evaluate``: joint position errors against the truth (``freipose eval``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from freipose.demo.context import DemoContext, session_labels, truth_to_calibrated
from freipose.demo.markers import step_results
from freipose.demo.presets import STIM_PART


@dataclass(frozen=True)
class _LabelScores:
    """The errors on the held-out labels, their failure modes and references, keypoint names."""

    methods: dict[str, Any]  # per method: median, p30, p70 JPE (mm)
    failure_modes: dict[str, Any]  # the voxel network's (P1), see freipose.nn.failure_modes
    references: dict[str, Any]  # per reference: median_mm, n
    keypoints: tuple[str, ...]
    comparisons: list[dict[str, Any]]  # paired differences, see freipose.nn.compare


def _on_labels(ctx: DemoContext, trained: dict[str, Any]) -> _LabelScores:
    """Voxel network vs. baseline on the held-out instants (cube on the true centre)."""
    from freipose.io.labels import read_labels_h5
    from freipose.nn.evaluate import evaluate_checkpoints, sanity_checks, write_report
    from freipose.nn.failure_modes import format_failure_modes

    ev = evaluate_checkpoints(
        {"voxel": trained["pose"]["checkpoint"], "baseline": trained["baseline"]["checkpoint"]},
        ctx.out / "labels" / "eval.h5",
        device=ctx.device,
    )
    sanity = sanity_checks(ev, read_labels_h5(ctx.out / "labels" / "train.h5").points3d)
    summary = write_report(ctx.out / "evaluation" / "labels", ev.errors, ev.keypoints, sanity)
    res: dict[str, Any] = {}
    ctx.say("  cube on the true centre, held-out instants (what `freipose eval` reports):")
    for name, s in summary.items():
        o = s["overall"]
        res[name] = {"median": o["median"], "p30": o["p30"], "p70": o["p70"]}
        ctx.say(f"    {name:10s} median JPE {o['median']:7.2f} mm "
                f"(30-70 %: {o['p30']:.2f}-{o['p70']:.2f})")  # fmt: skip
    ctx.say("  references that look at no image (the training labels' median pose):")
    for name, r in sanity.references.items():
        ctx.say(f"    {name}: median JPE {r['median_mm']:.2f} mm")
    nets = [c for c in sanity.comparisons if c.b == "baseline"]
    if nets:
        ctx.say("  paired on the same instants (95 % interval from a block bootstrap):")
    for c in nets:
        ctx.say(f"    {c.sentence()}")
    modes = sanity.failure_modes["voxel_P1"]
    ctx.say("  failure modes of the voxel network (P1):")
    for line in format_failure_modes({**modes, "warnings": []}):
        ctx.say("  " + line)
    for w in sanity.warnings:
        ctx.say("  " + w)
    comparisons = [c.to_dict() for c in sanity.comparisons]
    return _LabelScores(res, modes, sanity.references, ev.keypoints, comparisons)


def _pipeline(ctx: DemoContext, keypoints: tuple[str, ...]) -> dict[str, Any]:
    """The whole pipeline (detector + voxel network) on every frame of every session.

    Also the stimulated keypoint's errors inside and outside the stimulation, since the
    analysis looks for the effect there.
    """
    from freipose.io.poses import read_poses_h5
    from freipose.nn.evaluate import jpe, write_report
    from freipose.nn.failure_modes import failure_modes

    align = step_results(ctx.out, "calibrate")["alignment"]
    pipe: dict[str, np.ndarray] = {}
    modes: dict[str, Any] = {}
    stim: dict[str, dict[str, Any] | None] = {}
    for s in ctx.preset.analysed:
        data = read_poses_h5(ctx.poses_dir / f"{s.name}.poses.h5")
        truth = session_labels(ctx, s.name)
        gt = truth_to_calibrated(truth.points3d, align)
        rows = {int(f): i for i, f in enumerate(truth.frame_index)}
        idx = np.array([rows[int(f)] for f in data.frame_index])
        name = f"{s.name} ({s.split})"
        pipe[name] = jpe(data.poses, gt[idx])
        if data.skeleton is not None:
            modes[name] = failure_modes(data.poses, gt[idx], data.skeleton, name)
        stim[name] = _stimulated_part(ctx, s.name, data.poses, gt[idx], tuple(data.keypoints),
                                      np.asarray(data.frame_index, dtype=float))  # fmt: skip
    summary = write_report(ctx.out / "evaluation" / "pipeline", pipe, keypoints)
    res: dict[str, Any] = {}
    ctx.say("  whole pipeline (detector + voxel network, every frame, vs. the truth):")
    for name, s in summary.items():
        o = s["overall"]
        res[name] = {"median": o["median"], "missing": o.get("missing", 0)}
        if name in modes:
            res[name]["failure_modes"] = modes[name]
        ctx.say(f"    {name:22s} median JPE {o['median']:7.2f} mm over {o['n']} keypoints")
        if stim.get(name) is not None:
            res[name]["stimulated_part"] = stim[name]
            _say_stimulated(ctx, name, stim[name])
        for w in modes.get(name, {}).get("warnings", []):
            ctx.say("    " + w)
    return res


def stimulated_part_errors(
    pred: np.ndarray,
    truth: np.ndarray,
    times: np.ndarray,
    windows: np.ndarray,
    onset_delay_s: float,
    margin_s: float,
) -> dict[str, Any]:
    """The stimulated keypoint in the frames the analysis calls stimulated, and in the rest.

    The frames are split by the analysis's own rule
    (:func:`freipose.analysis.study.label_frames`): stimulated from ``start +
    onset_delay_s`` to ``end`` of a window, the rest further than ``margin_s`` from every
    window. Heights are world z (up, after the calibration's origin frame).

    Args:
        pred: (T, 3) predicted positions (mm), NaN where missing.
        truth: (T, 3) true positions (mm).
        times: (T,) frame times (s).
        windows: (W, 2) sorted, non-overlapping stimulation windows (start, end) in s.
        onset_delay_s: the analysis's onset delay.
        margin_s: the analysis's margin.

    Returns:
        ``stimulated`` and ``rest``: frame count ``n``, ``median_error_mm`` and
        ``median_height_error_mm`` (predicted minus true); ``lift_true_mm`` and
        ``lift_pred_mm``: mean height in the stimulated frames minus that in the rest.
    """
    from freipose.analysis.study import NOT_STIMULATED, STIMULATED, label_frames

    labels = label_frames(times, windows, onset_delay_s, margin_s)
    ok = np.isfinite(pred).all(-1)
    err = np.linalg.norm(pred - truth, axis=-1)
    dz = pred[:, 2] - truth[:, 2]
    masks = {"stimulated": (labels == STIMULATED) & ok, "rest": (labels == NOT_STIMULATED) & ok}
    out: dict[str, Any] = {}
    for name, m in masks.items():
        n = int(m.sum())
        out[name] = {
            "n": n,
            "median_error_mm": float(np.median(err[m])) if n else None,
            "median_height_error_mm": float(np.median(dz[m])) if n else None,
        }
    s, r = masks["stimulated"], masks["rest"]
    if s.any() and r.any():
        out["lift_true_mm"] = float(truth[s, 2].mean() - truth[r, 2].mean())
        out["lift_pred_mm"] = float(pred[s, 2].mean() - pred[r, 2].mean())
    return out


def _stimulated_part(
    ctx: DemoContext,
    name: str,
    pred: np.ndarray,
    gt: np.ndarray,
    keypoints: tuple[str, ...],
    frames: np.ndarray,
) -> dict[str, Any] | None:
    """:func:`stimulated_part_errors` of the demo's stimulated keypoint in session ``name``."""
    from freipose.analysis.study import read_events

    events = ctx.session_dir(name) / "events.csv"
    if STIM_PART not in keypoints or not events.is_file():
        return None
    windows = read_events(events)
    k = keypoints.index(STIM_PART)
    a = ctx.preset.analysis
    return stimulated_part_errors(pred[:, k], gt[:, k], frames / ctx.preset.fps, windows,
                                  a["onset_delay_s"], a["margin_s"])  # fmt: skip


def lift_note(name: str, r: dict[str, Any]) -> str | None:
    """A plain sentence when the stimulated part's predicted height change disagrees with the truth.

    They disagree when they differ by more than half the true change and by at least 1 mm
    (an opposite sign always differs by more than the true change itself).

    Args:
        name: the recording.
        r: what :func:`stimulated_part_errors` returned for it.

    Returns:
        E.g. ``"The network does not reproduce the height change on rat1_day3: predicted
        -1.6 mm, true +5.4 mm (the opposite direction)."``; None when they agree or one is
        missing.
    """
    pred, true = r.get("lift_pred_mm"), r.get("lift_true_mm")
    if pred is None or true is None or not np.isfinite([pred, true]).all():
        return None
    if abs(pred - true) <= max(0.5 * abs(true), 1.0):
        return None
    figures = f"predicted {pred:+.1f} mm, true {true:+.1f} mm"
    if pred * true < 0:
        return (f"The network does not reproduce the height change on {name}: {figures} "
                "(the opposite direction).")  # fmt: skip
    if abs(pred) < abs(true):
        return f"The network reproduces only part of the height change on {name}: {figures}."
    return f"The network exaggerates the height change on {name}: {figures}."


def _say_stimulated(ctx: DemoContext, name: str, r: dict[str, Any]) -> None:
    """One line on the stimulated keypoint of session ``name``."""
    if "lift_true_mm" not in r:  # no stimulated or no rest frame with a pose
        return
    st, rest = r["stimulated"], r["rest"]
    ctx.say(
        f"      {STIM_PART} in the stimulated frames vs the rest: median error "
        f"{st['median_error_mm']:.1f} vs {rest['median_error_mm']:.1f} mm, height "
        f"{st['median_height_error_mm']:+.1f} vs {rest['median_height_error_mm']:+.1f} mm off; "
        f"mean height in the stimulated frames minus the rest {r['lift_pred_mm']:+.1f} mm "
        f"predicted, {r['lift_true_mm']:+.1f} mm true"
    )
    note = lift_note(name, r)
    if note:
        ctx.say(f"      {note}")


def run(ctx: DemoContext) -> dict[str, Any]:
    """Evaluate on the held-out labels and the whole pipeline on every session.

    Args:
        ctx: the demo run.

    Returns:
        ``labels`` (per method: median, p30, p70 JPE in mm), ``failure_modes`` (of the
        voxel network's P1: ``pairs``, ``bones``, ``warnings``, see
        :func:`freipose.nn.failure_modes.failure_modes`), ``references`` (per
        constant-pose reference: ``median_mm``, ``n``), ``comparisons`` (paired
        differences of the networks and against the reference, see
        :mod:`freipose.nn.compare`) and ``pipeline`` (per session:
        median JPE, missing keypoints, where the poses name their skeleton the
        ``failure_modes`` of every frame, and ``stimulated_part``: the stimulated keypoint's
        errors in the stimulated frames and in the rest, :func:`stimulated_part_errors`).
    """
    scores = _on_labels(ctx, step_results(ctx.out, "train"))
    return {
        "labels": scores.methods,
        "failure_modes": scores.failure_modes,
        "references": scores.references,
        "comparisons": scores.comparisons,
        "pipeline": _pipeline(ctx, scores.keypoints),
    }
