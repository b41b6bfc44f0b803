"""Step 6, ``evaluate``: joint position errors against the truth (``freipose eval``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from freipose.demo.context import DemoContext, session_labels, truth_to_calibrated
from freipose.demo.markers import step_results


@dataclass(frozen=True)
class _LabelScores:
    """The errors on the held-out labels and the labels' keypoint names."""

    methods: dict[str, Any]  # per method: median, p30, p70 JPE (mm)
    keypoints: tuple[str, ...]


def _on_labels(ctx: DemoContext, trained: dict[str, Any]) -> _LabelScores:
    """Voxel network vs. baseline on the held-out instants (cube on the true centre)."""
    from freipose.io.labels import read_labels_h5
    from freipose.nn.checkpoint import load_checkpoint
    from freipose.nn.dataset import MultiViewDataset
    from freipose.nn.evaluate import jpe, predict_dataset, write_report

    ev_path = ctx.out / "labels" / "eval.h5"
    lab = read_labels_h5(ev_path)
    ds = MultiViewDataset(lab, root=ev_path.parent)
    results: dict[str, np.ndarray] = {}
    keypoints = tuple(lab.keypoints)
    for sub in ("pose", "baseline"):
        model, config, _ = load_checkpoint(trained[sub]["checkpoint"], ctx.device)
        pred = predict_dataset(model, ds, batch_size=4)
        if config.model.kind == "voxel":
            results["voxel_P0"] = jpe(pred["P0"], pred["gt"])
            results["voxel_P1"] = jpe(pred["P1"], pred["gt"])
        else:
            results["baseline"] = jpe(pred["P1"], pred["gt"])
    summary = write_report(ctx.out / "evaluation" / "labels", results, keypoints)
    res: dict[str, Any] = {}
    ctx.say("  cube on the true centre, held-out instants (what `freipose eval` reports):")
    for name, s in summary.items():
        o = s["overall"]
        res[name] = {"median": o["median"], "p30": o["p30"], "p70": o["p70"]}
        ctx.say(f"    {name:10s} median JPE {o['median']:7.2f} mm "
                f"(30-70 %: {o['p30']:.2f}-{o['p70']:.2f})")  # fmt: skip
    return _LabelScores(res, keypoints)


def _pipeline(ctx: DemoContext, keypoints: tuple[str, ...]) -> dict[str, Any]:
    """The whole pipeline (detector + voxel network) on every frame of every session."""
    from freipose.io.poses import read_poses_h5
    from freipose.nn.evaluate import jpe, write_report

    align = step_results(ctx.out, "calibrate")["alignment"]
    pipe: dict[str, np.ndarray] = {}
    for s in ctx.preset.sessions:
        data = read_poses_h5(ctx.poses_dir / f"{s.name}.poses.h5")
        truth = session_labels(ctx, s.name)
        gt = truth_to_calibrated(truth.points3d, align)
        rows = {int(f): i for i, f in enumerate(truth.frame_index)}
        idx = np.array([rows[int(f)] for f in data.frame_index])
        pipe[f"{s.name} ({s.split})"] = jpe(data.poses, gt[idx])
    summary = write_report(ctx.out / "evaluation" / "pipeline", pipe, keypoints)
    res: dict[str, Any] = {}
    ctx.say("  whole pipeline (detector + voxel network, every frame, vs. the truth):")
    for name, s in summary.items():
        o = s["overall"]
        res[name] = {"median": o["median"], "missing": o.get("missing", 0)}
        ctx.say(f"    {name:22s} median JPE {o['median']:7.2f} mm over {o['n']} keypoints")
    return res


def run(ctx: DemoContext) -> dict[str, Any]:
    """Evaluate on the held-out labels and the whole pipeline on every session.

    Args:
        ctx: the demo run.

    Returns:
        ``labels`` (per method: median, p30, p70 JPE in mm) and ``pipeline`` (per session:
        median JPE and missing keypoints).
    """
    scores = _on_labels(ctx, step_results(ctx.out, "train"))
    return {"labels": scores.methods, "pipeline": _pipeline(ctx, scores.keypoints)}
