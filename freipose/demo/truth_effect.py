"""What the synthetic truth says about a significant variable of the demo's analysis.

The demo knows what the stimulation does: :func:`moved_keypoints` simulates the test day
again without the stimulation (the same seed gives the same behaviour, since the
stimulation only adds its offsets) and measures how far every true keypoint moves because
of it. :func:`truth_notes` turns that into one sentence per significant variable: a
variable of keypoints that the stimulation moves is an effect of the stimulation; one of
keypoints that it leaves in place is not, and the sentence adds how large the network's
error on those keypoints is inside and outside the stimulated frames: an error that
differs between them (by over 20 % and 1 mm) is a tracking error that follows the
stimulation, else the variable is a false positive of the test.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

MOVED_MM = 0.5  # a keypoint moved by the stimulation by more than this is "moved"


def moved_keypoints(preset: Any, seed: int) -> dict[str, float]:
    """How far the stimulation moves every true keypoint of one demo recording.

    Args:
        preset: the demo preset.
        seed: the recording's seed.

    Returns:
        Keypoint name -> the largest distance (mm) between its true position with and
        without the stimulation over the recording.
    """
    from freipose.demo.steps.synth import session_scene
    from freipose.skeleton import load_skeleton
    from freipose.synth.scene import build_scene

    cfg = session_scene(preset, seed)
    with_stim = build_scene(cfg).geometry.keypoints
    without = build_scene(dataclasses.replace(cfg, stimulation=None)).geometry.keypoints
    d = np.linalg.norm(with_stim - without, axis=-1).max(axis=0)
    return dict(zip(load_skeleton("rat").keypoints, (float(v) for v in d), strict=True))


def error_inside_outside(
    predicted: np.ndarray, truth: np.ndarray, labels: np.ndarray, keypoint: int
) -> tuple[float, float]:
    """Median 3D error of one keypoint in the stimulated and the not-stimulated frames.

    Args:
        predicted: (T, K, 3) predicted poses.
        truth: (T, K, 3) true poses, the same frames.
        labels: (T,) frame labels (1 stimulated, 0 not stimulated, -1 ignored).
        keypoint: the keypoint's index.

    Returns:
        (inside, outside) in mm (NaN where no frame is defined).
    """
    err = np.linalg.norm(predicted[:, keypoint] - truth[:, keypoint], axis=-1)

    def med(mask: np.ndarray) -> float:
        v = err[mask & np.isfinite(err)]
        return float(np.median(v)) if len(v) else float("nan")

    return med(labels == 1), med(labels == 0)


def truth_note(
    variable: Mapping[str, Any],
    moved: Mapping[str, float],
    errors: Mapping[str, tuple[float, float]] | None = None,
) -> str:
    """One sentence on what a significant variable is, from the truth.

    Args:
        variable: a significant variable (``variable``, ``rank``, ``keypoints``: names
            joined by ``;``).
        moved: :func:`moved_keypoints` of the test recording.
        errors: keypoint -> (inside, outside) median error of the predicted poses; None
            for the analysis of the true poses.

    Returns:
        The sentence.
    """
    kps = [k for k in str(variable.get("keypoints", "")).split(";") if k]
    name = f"{variable['variable']} (rank {variable['rank']})"
    stim = ", ".join(f"{k} (up to {d:.1f} mm)" for k, d in moved.items() if d > MOVED_MM)
    hit = {k: moved.get(k, 0.0) for k in kps if moved.get(k, 0.0) > MOVED_MM}
    if hit:
        parts = ", ".join(f"{k} by up to {d:.1f} mm" for k, d in hit.items())
        return (
            f"{name}: in the synthetic truth the stimulation moves {parts}: an effect of the "
            "stimulation."
        )
    largest = max((moved.get(k, 0.0) for k in kps), default=0.0)
    who = " and ".join(kps) or "its keypoints"
    verb = "moves" if len(kps) == 1 else "move"
    text = (
        f"{name}: in the synthetic truth {who} {verb} the same with and without the "
        f"stimulation (largest difference {largest:.2f} mm; the stimulation moves only "
        f"{stim or 'no keypoint'}), so this is not an effect of the stimulation"
    )
    if errors is None:
        return text + ": on the true poses it is a false positive of the test."
    known = [k for k in kps if k in errors and np.isfinite(errors[k]).all()]
    if not known:
        return text + "."
    errs = "; ".join(f"{k} {errors[k][0]:.1f} mm in the stimulated frames and "
                     f"{errors[k][1]:.1f} mm outside" for k in known)  # fmt: skip
    follows = any(abs(errors[k][0] - errors[k][1]) > max(1.0, 0.2 * min(errors[k]))
                  for k in known)  # fmt: skip
    verdict = (
        "a tracking error that follows the stimulation"
        if follows
        else "the error does not follow the stimulation: a false positive of the test"
    )
    return f"{text}; the network's median error on the test day is {errs}: {verdict}."


def truth_notes(
    variables: Sequence[Mapping[str, Any]],
    moved: Mapping[str, float],
    errors: Mapping[str, tuple[float, float]] | None = None,
) -> list[str]:
    """:func:`truth_note` of every significant variable that is not the stimulated part's.

    Args:
        variables: the significant variables.
        moved: :func:`moved_keypoints` of the test recording.
        errors: see :func:`truth_note`.

    Returns:
        The sentences, one per variable whose keypoints the stimulation does not move
        (variables of moved keypoints need no explanation).
    """
    out = []
    for v in variables:
        kps = [k for k in str(v.get("keypoints", "")).split(";") if k]
        if not any(moved.get(k, 0.0) > MOVED_MM for k in kps):
            out.append(truth_note(v, moved, errors))
    return out


def _errors(
    pred_path: Any, truth_path: Any, events: Any, analysis: Mapping[str, Any]
) -> dict[str, tuple[float, float]]:
    """Keypoint -> (inside, outside) median error of a poses file against the true poses."""
    from freipose.analysis.config import AttributionConfig
    from freipose.analysis.study import label_frames, read_events
    from freipose.io.poses import read_poses_h5

    pred, truth = read_poses_h5(pred_path), read_poses_h5(truth_path)
    common, ip, it = np.intersect1d(pred.frame_index, truth.frame_index, return_indices=True)
    cfg = AttributionConfig(**analysis)
    times = (common - truth.frame_index[0]) / truth.fps
    labels = label_frames(times, read_events(events), cfg.onset_delay_s, cfg.margin_s)
    p, t = pred.poses[ip].astype(np.float64), truth.poses[it].astype(np.float64)
    return {k: error_inside_outside(p, t, labels, i) for i, k in enumerate(truth.keypoints)}


def demo_truth_notes(ctx: Any, res: dict[str, Any], poses_dirs: Mapping[str, Any]) -> None:
    """Add ``truth_notes`` to every analysis of the demo's ``res`` and print them.

    Args:
        ctx: the demo run.
        res: the analyze step's results (``predicted``, ``truth``, ``smoothed``).
        poses_dirs: analysis key -> the folder of its poses files (``truth`` included).
    """
    test = ctx.preset.with_split("test")[0]
    moved = moved_keypoints(ctx.preset, test.seed)
    events = ctx.session_dir(test.name) / "events.csv"
    truth_file = poses_dirs["truth"] / f"{test.name}.poses.h5"
    for key, a in res.items():
        if not isinstance(a, dict) or "significant_variables" not in a or key not in poses_dirs:
            continue
        errors = None
        pred_file = poses_dirs[key] / f"{test.name}.poses.h5"
        if key != "truth" and pred_file.is_file() and truth_file.is_file():
            errors = _errors(pred_file, truth_file, events, ctx.preset.analysis)
        a["truth_notes"] = truth_notes(a["significant_variables"], moved, errors)
        for note in a["truth_notes"]:
            ctx.say(f"    [{key}] {note}")
