"""Step 6, ``evaluate``: joint position errors against the truth (``freipose eval``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from freipose.demo.context import DemoContext, session_labels, truth_to_calibrated
from freipose.demo.markers import step_results


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
    """The whole pipeline (detector + voxel network) on every frame of every session."""
    from freipose.io.poses import read_poses_h5
    from freipose.nn.evaluate import jpe, write_report
    from freipose.nn.failure_modes import failure_modes

    align = step_results(ctx.out, "calibrate")["alignment"]
    pipe: dict[str, np.ndarray] = {}
    modes: dict[str, Any] = {}
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
    summary = write_report(ctx.out / "evaluation" / "pipeline", pipe, keypoints)
    res: dict[str, Any] = {}
    ctx.say("  whole pipeline (detector + voxel network, every frame, vs. the truth):")
    for name, s in summary.items():
        o = s["overall"]
        res[name] = {"median": o["median"], "missing": o.get("missing", 0)}
        if name in modes:
            res[name]["failure_modes"] = modes[name]
        ctx.say(f"    {name:22s} median JPE {o['median']:7.2f} mm over {o['n']} keypoints")
        for w in modes.get(name, {}).get("warnings", []):
            ctx.say("    " + w)
    return res


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
        median JPE, missing keypoints and, where the poses name their skeleton, the
        ``failure_modes`` of every frame).
    """
    scores = _on_labels(ctx, step_results(ctx.out, "train"))
    return {
        "labels": scores.methods,
        "failure_modes": scores.failure_modes,
        "references": scores.references,
        "comparisons": scores.comparisons,
        "pipeline": _pipeline(ctx, scores.keypoints),
    }
