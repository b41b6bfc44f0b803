"""Step 7, ``analyze``: behavioural variables and attribution of the stimulation effect."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from freipose.demo.context import DemoContext, session_labels, truth_to_calibrated
from freipose.demo.markers import step_results
from freipose.demo.presets import STIM_PART
from freipose.io.atomic import atomic_write_text


def study_toml(ctx: DemoContext, study_dir: Path, poses_dir: Path | None = None) -> str:
    """The study manifest of the demo sessions (paths relative to ``study_dir``).

    Args:
        ctx: the demo run.
        study_dir: the folder the manifest is written to.
        poses_dir: the folder of the ``<session>.poses.h5`` files (default: the predictions).

    Returns:
        The manifest's TOML text.
    """
    poses_dir = ctx.poses_dir if poses_dir is None else poses_dir
    lines = [
        "# written by freipose demo: one animal, one condition, a train and a test recording",
        'skeleton = "rat"',
        "",
    ]
    for s in ctx.preset.sessions:
        poses = os.path.relpath(poses_dir / f"{s.name}.poses.h5", study_dir)
        events = os.path.relpath(ctx.session_dir(s.name) / "events.csv", study_dir)
        lines += [
            "[[recordings]]",
            f'name = "{s.name}"',
            f'poses = "{Path(poses).as_posix()}"',
            f'events = "{Path(events).as_posix()}"',
            'animal = "rat1"',
            'condition = "paw_stimulation"',
            f'split = "{s.split}"',
            "",
        ]
    return "\n".join(lines)


def _write_truth_poses(ctx: DemoContext, folder: Path) -> None:
    """The true keypoints of every session as poses files (calibrated world frame)."""
    from freipose.io.calibration import load_calibration
    from freipose.io.poses import PoseData, write_poses_h5
    from freipose.skeleton import load_skeleton

    align = step_results(ctx.out, "calibrate")["alignment"]
    rig = load_calibration(ctx.calibration)
    skel = load_skeleton("rat")
    for s in ctx.preset.sessions:
        path = folder / f"{s.name}.poses.h5"
        if path.is_file():
            continue
        lab = session_labels(ctx, s.name)
        poses = truth_to_calibrated(lab.points3d, align)
        data = PoseData(
            poses=poses,
            confidence=np.ones(poses.shape[:2]),
            keypoints=tuple(lab.keypoints),
            frame_index=np.asarray(lab.frame_index),
            fps=ctx.preset.fps,
            calibration=rig,
            skeleton=skel,
            provenance={"source": "freipose demo: true keypoints of the synthetic session"},
        )
        folder.mkdir(parents=True, exist_ok=True)
        write_poses_h5(data, path)


def _analyze(ctx: DemoContext, study: Path, text: str, results: Path) -> dict[str, Any]:
    """Run ``freipose analyze`` on the manifest ``text`` (written to ``study``) into ``results``.

    Returns:
        The classification scores, the 10 best single variables, the share of them that
        belong to the stimulated body part and the number of significant variables.
    """
    from freipose.analysis.config import AttributionConfig
    from freipose.analysis.report import analyze_study
    from freipose.analysis.variables import VariableConfig

    if not study.is_file() or study.read_text(encoding="utf-8") != text:
        atomic_write_text(study, text)
    acfg = AttributionConfig(**ctx.preset.analysis)
    vcfg = VariableConfig(stft_window=ctx.preset.stft_window)
    result = analyze_study(
        study, results, None, "world", vcfg, acfg, say=lambda m: ctx.say("    " + m)
    )
    att = result.attribution.sort_values("f1", ascending=False)
    top = att.head(10)
    parts = top["part"].tolist()
    share = float(np.mean([pt == STIM_PART for pt in parts])) if parts else 0.0
    res = {
        "classification": json.loads(result.classification.to_json(orient="records")),
        "top_variables": json.loads(
            top[["variable", "part", "f1", "p_value", "p_adjusted", "significant"]].to_json(
                orient="records"
            )
        ),
        "top10_share_stimulated_part": share,
        "significant": int(att["significant"].sum()),
    }
    ctx.say(
        f"    -> {int(round(share * 10))} of the 10 best single variables belong to the "
        f"stimulated {STIM_PART} (best: {top.iloc[0]['variable']}, F1 "
        f"{top.iloc[0]['f1']:.2f}); {res['significant']} significant after the "
        "autocorrelation-corrected, Bonferroni-adjusted test"
    )
    return res


def run(ctx: DemoContext) -> dict[str, Any]:
    """Analyze the predicted poses and, for comparison, the true keypoints.

    Args:
        ctx: the demo run.

    Returns:
        ``stimulated_part`` and what :func:`_analyze` returned for ``predicted`` and
        ``truth``.
    """
    out = ctx.out / "analysis"
    out.mkdir(parents=True, exist_ok=True)
    ctx.say("  on the predicted poses:")
    pred = _analyze(ctx, out / "study.toml", study_toml(ctx, out), out / "results")
    # The same analysis on the true keypoints: what perfect tracking would show.
    ctx.say("  on the true keypoints (for comparison: perfect tracking):")
    truth_dir = out / "truth_poses"
    _write_truth_poses(ctx, truth_dir)
    truth = _analyze(
        ctx, out / "study_truth.toml", study_toml(ctx, out, truth_dir), out / "results_truth"
    )
    return {"stimulated_part": STIM_PART, "predicted": pred, "truth": truth}
