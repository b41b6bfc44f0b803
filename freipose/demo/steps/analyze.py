"""Step 7, ``analyze``: behavioural variables and attribution of the stimulation effect."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from freipose.demo.context import DemoContext, session_labels, truth_to_calibrated
from freipose.demo.markers import step_results
from freipose.demo.presets import STIM_PART
from freipose.demo.truth_effect import demo_truth_notes
from freipose.io.atomic import atomic_write_text

if TYPE_CHECKING:
    import pandas as pd

HELD_OUT_INSTANTS = 24  # held-out instants predicted to measure the network's error


def study_toml(ctx: DemoContext, study_dir: Path, poses_dir: Path | None = None) -> str:
    """The study manifest of the demo sessions (paths relative to ``study_dir``).

    Args:
        ctx: the demo run.
        study_dir: the folder the manifest is written to.
        poses_dir: the folder of the ``<session>.poses.h5`` files (default: the predictions).

    Returns:
        The manifest's TOML text.
    """
    from freipose.analysis.study import recording_entry

    poses_dir = ctx.poses_dir if poses_dir is None else poses_dir
    header = (
        "# written by freipose demo: one animal, one condition, a train and a test recording\n"
        'skeleton = "rat"\n\n'
    )
    entries = []
    for s in ctx.preset.analysed:
        poses = os.path.relpath(poses_dir / f"{s.name}.poses.h5", study_dir)
        events = os.path.relpath(ctx.session_dir(s.name) / "events.csv", study_dir)
        entries.append(recording_entry(s.name, Path(poses).as_posix(), Path(events).as_posix(),
                                       "rat1", "paw_stimulation", s.split))  # fmt: skip
    return header + "\n".join(entries)


def _write_truth_poses(ctx: DemoContext, folder: Path) -> None:
    """The true keypoints of every session as poses files (calibrated world frame)."""
    from freipose.io.calibration import load_calibration
    from freipose.io.poses import PoseData, write_poses_h5
    from freipose.skeleton import load_skeleton

    align = step_results(ctx.out, "calibrate")["alignment"]
    rig = load_calibration(ctx.calibration)
    skel = load_skeleton("rat")
    for s in ctx.preset.analysed:
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


def analyze_poses(ctx: DemoContext, study: Path, text: str, results: Path) -> dict[str, Any]:
    """Run ``freipose analyze`` on the manifest ``text`` (written to ``study``) into ``results``.

    Returns:
        The balanced accuracy, the rank (1 = best), name and F1 of the stimulated part's
        best single variable, the classification scores, the 10 best single variables, the
        share of them that belong to the stimulated body part and the number of
        significant variables.
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
    att = ranked(result.attribution)
    top = att.head(10)
    parts = top["part"].tolist()
    share = float(np.mean([pt == STIM_PART for pt in parts])) if parts else 0.0
    stim = np.flatnonzero(att["part"].to_numpy() == STIM_PART)
    res = {
        "balanced_accuracy": float(result.classification["balanced_accuracy"].iloc[0]),
        "stimulated_best_rank": int(stim[0]) + 1 if stim.size else None,
        "stimulated_best_variable": str(att["variable"].iloc[stim[0]]) if stim.size else None,
        "stimulated_best_f1": float(att["f1"].iloc[stim[0]]) if stim.size else None,
        "classification": json.loads(result.classification.to_json(orient="records")),
        "top_variables": json.loads(
            top[["variable", "part", "f1", "p_value", "p_adjusted", "significant"]].to_json(
                orient="records"
            )
        ),
        "top10_share_stimulated_part": share,
        "significant": int(att["significant"].sum()),
        "significant_variables": significant_variables(att),
    }
    ctx.say(
        f"    -> {int(round(share * 10))} of the 10 best single variables belong to the "
        f"stimulated {STIM_PART} (best: {top.iloc[0]['variable']}, F1 "
        f"{top.iloc[0]['f1']:.2f}); significant after the autocorrelation-corrected, "
        f"Bonferroni-adjusted test: {significant_text(res)}"
    )
    return res


def ranked(attribution: pd.DataFrame) -> pd.DataFrame:
    """The single variables (``attribution.csv`` rows) best first: row i has rank i + 1."""
    return attribution.sort_values("f1", ascending=False, kind="stable").reset_index(drop=True)


def significant_variables(att: pd.DataFrame) -> list[dict[str, Any]]:
    """The significant single variables of :func:`ranked` rows, best first.

    Returns:
        Per variable: ``variable``, ``rank`` (1 = best F1), ``f1``, ``p_value``,
        ``p_adjusted`` (Bonferroni) and ``keypoints`` (joined by ``;``).
    """
    rows = np.flatnonzero(att["significant"].to_numpy(dtype=bool))
    return [
        {"variable": str(att["variable"].iloc[i]), "rank": int(i) + 1,
         "f1": float(att["f1"].iloc[i]), "p_value": float(att["p_value"].iloc[i]),
         "p_adjusted": float(att["p_adjusted"].iloc[i]),
         "keypoints": str(att["keypoints"].iloc[i]) if "keypoints" in att else ""}
        for i in rows
    ]  # fmt: skip


def significant_text(res: dict[str, Any]) -> str:
    """How many single variables are significant, naming each with its rank and F1.

    Args:
        res: what :func:`analyze_poses` returned.

    Returns:
        E.g. ``"1 (local_z[Tail], rank 85, F1 0.61)"`` or ``"0"``.
    """
    named = [f"{v['variable']}, rank {v['rank']}, F1 {v['f1']:.2f}"
             for v in res.get("significant_variables", [])]  # fmt: skip
    listed = f" ({'; '.join(named)})" if named else ""
    return f"{res['significant']}{listed}"


def raw_vs_smoothed(raw: dict[str, Any], smoothed: dict[str, Any]) -> list[tuple[str, str, str]]:
    """The analysis figures of the raw and the smoothed predictions, as the demo prints them.

    Args:
        raw: what :func:`analyze_poses` returned for the predicted poses.
        smoothed: the same for the smoothed predicted poses.

    Returns:
        (figure, raw, smoothed) rows of text: the balanced accuracy on the test day, the
        best single variable with its F1, the rank and F1 of the stimulated part's best
        variable and the number of significant variables.
    """

    def best(r: dict[str, Any]) -> str:
        t = r["top_variables"][0] if r.get("top_variables") else None
        return f"{t['variable']} (F1 {t['f1']:.2f})" if t else "-"

    def stim(r: dict[str, Any]) -> str:
        if r.get("stimulated_best_rank") is None:
            return "-"
        return (f"{r['stimulated_best_variable']} (rank {r['stimulated_best_rank']}, "
                f"F1 {r['stimulated_best_f1']:.2f})")  # fmt: skip

    return [
        ("balanced accuracy of the classifier on the test day",
         f"{raw['balanced_accuracy']:.2f}", f"{smoothed['balanced_accuracy']:.2f}"),
        ("best single variable", best(raw), best(smoothed)),
        (f"best {STIM_PART} variable", stim(raw), stim(smoothed)),
        ("significant single variables", significant_text(raw), significant_text(smoothed)),
    ]  # fmt: skip


def run(ctx: DemoContext) -> dict[str, Any]:
    """Analyze the predicted poses, the smoothed predictions and the true keypoints.

    Args:
        ctx: the demo run.

    Returns:
        ``stimulated_part``; what :func:`analyze_poses` returned for ``predicted``, ``truth``
        and ``smoothed``; ``smooth``: the raw-vs-smoothed figure (``figure``), the
        balanced accuracy and the stimulated part's best rank, raw and smoothed, and what
        the held-out error of the network was measured on.
    """
    out = ctx.out / "analysis"
    out.mkdir(parents=True, exist_ok=True)
    p = ctx.preset
    ctx.say(
        f"  the classifier trains on {p.with_split('train')[0].name} and is tested on "
        f"{p.with_split('test')[0].name}; the labeled {p.with_split('label')[0].name} is "
        "left out (the network fits its labeled frames better than any other day's, and a "
        "classifier trained on them does not carry over)"
    )
    ctx.say("  on the predicted poses:")
    pred = analyze_poses(ctx, out / "study.toml", study_toml(ctx, out), out / "results")
    # The same analysis on the true keypoints: what perfect tracking would show.
    ctx.say("  on the true keypoints (for comparison: perfect tracking):")
    truth_dir = out / "truth_poses"
    _write_truth_poses(ctx, truth_dir)
    truth = analyze_poses(
        ctx, out / "study_truth.toml", study_toml(ctx, out, truth_dir), out / "results_truth"
    )
    res = {"stimulated_part": STIM_PART, "predicted": pred, "truth": truth}
    smoothed_dir = out / "smoothed_poses"
    smooth_info = _smooth_predictions(ctx, smoothed_dir)
    ctx.say("  on the smoothed predicted poses (freipose smooth):")
    res["smoothed"] = analyze_poses(
        ctx,
        out / "study_smoothed.toml",
        study_toml(ctx, out, smoothed_dir),
        out / "results_smoothed",
    )
    ctx.say(_side_by_side(pred, res["smoothed"]))
    # what the truth says about significant variables of parts the stimulation leaves alone
    dirs = {"predicted": ctx.poses_dir, "truth": truth_dir, "smoothed": smoothed_dir}
    demo_truth_notes(ctx, res, dirs)
    test = p.with_split("test")[0].name
    res["smooth"] = {
        **smooth_info,
        "figure": str(_trajectory_figure(ctx, test, smoothed_dir, out / "smoothed_vs_raw.png")),
        "balanced_accuracy": {"raw": pred["balanced_accuracy"],
                              "smoothed": res["smoothed"]["balanced_accuracy"]},
        "stimulated_best_rank": {"raw": pred["stimulated_best_rank"],
                                 "smoothed": res["smoothed"]["stimulated_best_rank"]},
    }  # fmt: skip
    return res


def _side_by_side(raw: dict[str, Any], smoothed: dict[str, Any]) -> str:
    """:func:`raw_vs_smoothed` as terminal lines: each figure, raw vs smoothed."""
    rows = raw_vs_smoothed(raw, smoothed)
    return "    raw vs smoothed:\n" + "\n".join(f"      {n}: {a} vs {b}" for n, a, b in rows)


def _smooth_predictions(ctx: DemoContext, folder: Path) -> dict[str, Any]:
    """Smooth every session's predictions into ``folder`` (kept if already there).

    The standard deviation includes the pose network's error on the held-out labels
    (``labels/eval.h5``) where they have enough instants per keypoint.

    Returns:
        ``held_out_error`` (what it was measured on, or why not) and ``files``.
    """
    from freipose.predict.smooth import smooth_file
    from freipose.predict.smooth_error import ValidationLabelsError, model_validation_error

    model = step_results(ctx.out, "train")["pose"]["checkpoint"]
    todo = [s.name for s in ctx.preset.analysed if not (folder / f"{s.name}.poses.h5").is_file()]
    held_out, note = None, "not needed: every session was smoothed before"
    if todo:
        try:
            held_out = model_validation_error(
                model,
                ctx.out / "labels" / "eval.h5",
                device=ctx.device,
                max_instants=HELD_OUT_INSTANTS,
            )
            note = held_out.source
        except ValidationLabelsError as exc:
            note = f"left out: {exc}"
        ctx.say(f"  smoothing the predictions; held-out error of the network: {note}")
    folder.mkdir(parents=True, exist_ok=True)
    files = []
    for s in ctx.preset.analysed:
        dst = folder / f"{s.name}.poses.h5"
        if not dst.is_file():
            smooth_file(ctx.poses_dir / f"{s.name}.poses.h5", dst, error_floor=held_out)
        files.append(str(dst))
    return {"held_out_error": note, "files": files}


def figure_seconds(events: np.ndarray, windows: int = 2) -> float:
    """How long a trajectory figure runs to show ``windows`` whole stimulation windows.

    Args:
        events: (W, 2) stimulation windows (start, end) in s, as in ``events.csv``.
        windows: how many windows to show.

    Returns:
        The end of the ``windows``-th window plus 1 s (6 s when there is no window).
    """
    if len(events) == 0:
        return 6.0
    return float(events[min(windows, len(events)) - 1, 1]) + 1.0


def _trajectory_figure(ctx: DemoContext, session: str, smoothed_dir: Path, path: Path) -> Path:
    """Raw vs smoothed trajectories (with the 2-sigma band and the truth) of a few keypoints."""
    from freipose.demo.context import save_png
    from freipose.io.figures import new_figure
    from freipose.io.poses import read_poses_h5

    raw = read_poses_h5(ctx.poses_dir / f"{session}.poses.h5")
    sm = read_poses_h5(smoothed_dir / f"{session}.poses.h5")
    lab = session_labels(ctx, session)
    gt = truth_to_calibrated(lab.points3d, step_results(ctx.out, "calibrate")["alignment"])
    rows = {int(f): i for i, f in enumerate(lab.frame_index)}
    gt = gt[[rows[int(f)] for f in raw.frame_index]]
    names = [k for k in (STIM_PART, "Nose", "Tail") if k in raw.keypoints]
    t = (raw.frame_index - raw.frame_index[0]) / raw.fps
    events = np.loadtxt(ctx.session_dir(session) / "events.csv", delimiter=",", skiprows=1, ndmin=2)
    n = min(len(t), int(round(figure_seconds(events) * raw.fps)))
    fig = new_figure(figsize=(11.0, 2.2 * len(names)))
    axes = fig.subplots(len(names), 1, sharex=True, squeeze=False)[:, 0]
    for ax, name in zip(axes, names, strict=True):
        for a, b in events:
            if a < t[n - 1]:
                ax.axvspan(a, min(b, t[n - 1]), color="0.92", lw=0)
        k = raw.keypoints.index(name)
        mean, std = sm.poses[:n, k, 2], sm.extra["smooth_std"][:n, k, 2]
        ax.fill_between(t[:n], mean - 2 * std, mean + 2 * std, color="C1", alpha=0.25,
                        lw=0, label="smoothed ±2 sd")  # fmt: skip
        ax.plot(t[:n], raw.poses[:n, k, 2], ".", color="0.5", ms=3, label="raw prediction")
        ax.plot(t[:n], mean, color="C1", lw=1.2, label="smoothed")
        ax.plot(t[:n], gt[:n, k, 2], color="k", lw=0.8, ls="--", label="truth")
        ax.set_ylabel(f"{name}\nz (mm)")
    axes[0].legend(loc="upper right", fontsize=7, ncol=4)
    axes[-1].set_xlabel(f"time (s), session {session}; grey: stimulation")
    save_png(fig, path)
    return path
