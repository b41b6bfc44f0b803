"""Step 3, ``labels``: import training and evaluation labels (``freipose labels``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from freipose.demo.context import DemoContext, session_labels, truth_to_calibrated
from freipose.demo.markers import step_results


def _pick(n_total: int, n: int) -> np.ndarray:
    """(<= n,) evenly spread, distinct indices into ``n_total`` items."""
    return np.unique(np.linspace(0, n_total - 1, min(n, n_total)).round().astype(int))


def _labels_file(
    ctx: DemoContext, names: list[str], per_session: int, mode: str, path: Path
) -> dict[str, Any]:
    """Import labels of ``names`` into ``path`` with the labels library (``freipose labels``).

    Args:
        ctx: the demo run.
        names: the sessions whose labels are imported.
        per_session: time instants picked (evenly) from each session.
        mode: ``"triangulate"``: the 2D labels of the visible keypoints (plus 1 px labelling
            noise, as from a 2D labelling tool) are triangulated with the calibrated rig
            (training labels); ``"truth"``: the true 3D keypoints mapped into the calibrated
            world frame (evaluation labels).
        path: the labels file written.

    Returns:
        ``path`` and ``instants``; for ``"triangulate"`` also the median reprojection error
        (px), the median distance of the triangulated keypoints from the truth (mm) and the
        fraction of keypoints labeled in 3D.
    """
    from freipose.geometry import reprojection_errors
    from freipose.io.calibration import load_calibration
    from freipose.io.labels import write_labels_h5
    from freipose.labels.importing import ImportOptions, SourceLabels, build_labelset

    rig = load_calibration(ctx.calibration)
    align = step_results(ctx.out, "calibrate")["alignment"]
    rng = np.random.default_rng(0)
    sources, truths = [], []
    for name in names:
        lab = session_labels(ctx, name)
        sub = lab.select(_pick(len(lab), per_session))
        vis = sub.visible2d if sub.visible2d is not None else np.isfinite(sub.points2d).all(-1)
        p2 = np.where(vis[..., None], sub.points2d, np.nan)
        truth3d = truth_to_calibrated(sub.points3d, align)
        if mode == "triangulate":
            p2 = p2 + rng.normal(0.0, 1.0, p2.shape)
        info = sub.sessions[name]
        sources.append(
            SourceLabels(
                source=str(ctx.session_dir(name) / "labels.h5"),
                session=name,
                cameras=list(sub.cameras),
                keypoints=list(sub.keypoints),
                frame_index=np.asarray(sub.frame_index),
                points2d=p2,
                visible2d=vis,
                points3d=None if mode == "triangulate" else truth3d,
                videos={c: (ctx.session_dir(name) / v).resolve() for c, v in info.videos.items()},
                fps=info.fps,
            )
        )
        truths.append(truth3d)
    opts = ImportOptions(calibration=rig, calibration_source=str(ctx.calibration), threshold=8.0)
    labels = build_labelset(sources, opts, path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_labels_h5(labels, path)
    out: dict[str, Any] = {"path": str(path), "instants": len(labels)}
    if mode == "triangulate":
        p3 = labels.points3d
        pts = np.moveaxis(labels.points2d, 1, 2)  # (N, K, V, 2)
        err = reprojection_errors(p3, pts, labels.rig_for(names[0]).subset(labels.cameras))
        d = np.linalg.norm(p3 - np.concatenate(truths), axis=-1)
        out["median_reprojection_px"] = float(np.nanmedian(err))
        out["median_3d_vs_truth_mm"] = float(np.nanmedian(d))
        out["labeled_fraction"] = float(np.isfinite(p3).all(-1).mean())
    return out


def _say_sources(ctx: DemoContext, names: list[str], use: str) -> None:
    """Name the generator's label files that the next labels file is imported from."""
    files = ", ".join(str((ctx.session_dir(n) / "labels.h5").relative_to(ctx.out)) for n in names)
    ctx.say(f"  {files} (read: the synthetic generator's labels of every frame, standing in "
            f"for a labelling tool's export) -> the {use} labels")  # fmt: skip


def run(ctx: DemoContext) -> dict[str, Any]:
    """Write ``labels/train.h5`` (triangulated) and ``labels/eval.h5`` (held-out truth).

    Args:
        ctx: the demo run.

    Returns:
        ``train`` and ``eval``: what :func:`_labels_file` returned for each file.
    """
    p = ctx.preset
    train = [s.name for s in p.with_split("label")]
    test = [s.name for s in p.with_split("test")]
    _say_sources(ctx, train, "training")
    tr = _labels_file(
        ctx, train, p.label_instants // len(train), "triangulate", ctx.out / "labels" / "train.h5"
    )
    ctx.say(
        f"  labels/train.h5 (written: the training labels): {tr['instants']} instants of "
        f"{', '.join(train)}; 2D labels of the visible keypoints triangulated with the "
        f"calibrated rig: median reprojection {tr['median_reprojection_px']:.2f} px, "
        f"{tr['median_3d_vs_truth_mm']:.2f} mm from the truth, "
        f"{100 * tr['labeled_fraction']:.0f} % of keypoints labeled in 3D"
    )
    _say_sources(ctx, test, "evaluation")
    ev = _labels_file(
        ctx, test, p.eval_instants // len(test), "truth", ctx.out / "labels" / "eval.h5"
    )
    ctx.say(
        f"  labels/eval.h5 (written: the evaluation labels): {ev['instants']} held-out "
        f"instants of {', '.join(test)} with the true 3D keypoints (for evaluation only)"
    )
    return {"train": tr, "eval": ev}
