"""Step 8, ``report``: ``OUTDIR/report.html`` with every step's numbers and figures."""

from __future__ import annotations

import html
import json
import os
from pathlib import Path
from typing import Any

from freipose import __version__
from freipose.demo.context import DemoContext
from freipose.demo.markers import STEPS, read_marker
from freipose.demo.presets import STIM_PART
from freipose.io.atomic import atomic_write_text

_STYLE = (
    "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto;line-height:1.4}"
    "table{border-collapse:collapse;margin:0.5em 0}td,th{border:1px solid #bbb;"
    "padding:2px 8px;font-size:90%}figure{display:inline-block;margin:0.5em}"
    "figcaption{font-size:85%;color:#444}img{max-width:100%}</style></head><body>"
)


def _rel(ctx: DemoContext, p: Path | str) -> str:
    """``p`` relative to the demo folder, with forward slashes (a link in the report)."""
    return Path(os.path.relpath(Path(p), ctx.out)).as_posix()


def _img(ctx: DemoContext, p: Path, caption: str, width: int | None = None) -> str:
    """A ``<figure>`` of the image ``p`` (or a "missing figure" note)."""
    if not p.is_file():
        return f"<p><em>missing figure {html.escape(_rel(ctx, p))}</em></p>"
    w = f' width="{width}"' if width else ""
    return (
        f'<figure><img src="{html.escape(_rel(ctx, p))}"{w} alt="{html.escape(caption)}">'
        f"<figcaption>{html.escape(caption)}</figcaption></figure>"
    )


def _table(header: list[str], rows: list[list[Any]]) -> str:
    """An HTML table; floats with 3 significant digits (whole numbers from 1000 on)."""

    def cell(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}"
        return html.escape(str(v))

    h = "".join(f"<th>{html.escape(x)}</th>" for x in header)
    body = "".join("<tr>" + "".join(f"<td>{cell(v)}</td>" for v in r) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


def _head(ctx: DemoContext, markers: dict[str, dict[str, Any]]) -> list[str]:
    """The page head, the introduction and the table of step run times."""
    p = ctx.preset
    times = [[s, markers[s].get("seconds", float("nan"))] for s in STEPS if s != "report"]
    return [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>FreiPose demo ({html.escape(p.name)})</title>",
        _STYLE,
        f"<h1>FreiPose demo: preset <code>{html.escape(p.name)}</code></h1>",
        f"<p>freipose {html.escape(__version__)}. Synthetic data: a rat in a 600 mm open field "
        f"filmed by {p.n_cameras} cameras ({p.size[0]}x{p.size[1]} px, {p.fps:g} fps), "
        f"{len(p.sessions)} sessions of {p.session_frames} frames with the {STIM_PART} "
        f"stimulated ({html.escape(json.dumps(p.stimulation))}). Every step ran the same "
        "library code as the <code>freipose</code> commands; "
        "<code>examples/workflow.sh</code> runs them one by one.</p>",
        "<h2>Steps and run times</h2>" + _table(["step", "seconds"], times),
    ]


def _calibration(ctx: DemoContext, cal: dict[str, Any]) -> list[str]:
    """Steps 1-2: the per-camera errors against the true rig and the calibration figures."""
    parts = ["<h2>1-2. Calibration</h2>"]
    comp_path = ctx.out / "calibration" / "comparison.json"
    if comp_path.is_file():
        comp = json.loads(comp_path.read_text())
        rows = [
            [c, dc, rot, f[0], f[1]]
            for c, dc, rot, f in zip(
                comp["cameras"], comp["center_mm"], comp["rotation_deg"], comp["focal_percent"]
            )
        ]
        parts.append(
            "<p>Board videos calibrated with <code>freipose calib --origin-frame 0</code>; "
            "errors against the true rig after aligning the world frames "
            f"(scale {comp['scale']:.4f}).</p>"
            + _table(["camera", "centre mm", "rotation deg", "fx %", "fy %"], rows)
        )
    parts.append(_img(ctx, ctx.out / "calibration" / "comparison.png", "calibration errors"))
    rep = ctx.out / "calibration" / "report"
    parts.append(_img(ctx, rep / "rig_3d.png", "calibrated rig", 420))
    for e in sorted(rep.glob("errors_*.png"))[:2]:
        parts.append(_img(ctx, e, f"reprojection errors {e.stem[7:]}", 360))
    if cal.get("summary"):
        s = cal["summary"]
        parts.append(
            f"<p>Largest errors: camera centre {s['max_center_mm']:.2f} mm, rotation "
            f"{s['max_rotation_deg']:.3f} deg, focal length {s['max_focal_percent']:.2f} %, "
            f"reprojection RMS {s['max_rms_px']:.2f} px.</p>"
        )
    return parts


def _labels(lab: dict[str, Any]) -> list[str]:
    """Step 3: the imported training and evaluation labels."""
    if not lab:
        return []
    tr, ev = lab["train"], lab["eval"]
    return [
        "<h2>3. Labels</h2>"
        f"<p><code>labels/train.h5</code>: {tr['instants']} time instants; 2D labels of the "
        "visible keypoints (1 px noise) triangulated with the calibrated rig: median "
        f"reprojection error {tr['median_reprojection_px']:.2f} px, "
        f"{tr['median_3d_vs_truth_mm']:.2f} mm from the true 3D keypoints. "
        f"<code>labels/eval.h5</code>: {ev['instants']} held-out instants of the test "
        "session with the true keypoints.</p>"
    ]


def _training(ctx: DemoContext, trained: dict[str, Any]) -> list[str]:
    """Step 4: the detector's metrics and the training curves."""
    parts = ["<h2>4. Training</h2>"]
    det = trained.get("detector", {}).get("metrics", {})
    if det:
        keys = [k for k in ("recall", "median_center_error_mm", "cpu_fps", "train_seconds")
                if k in det]  # fmt: skip
        parts.append(_table(["detector metric", "value"], [[k, det[k]] for k in keys]))
    parts.append(_img(ctx, ctx.train_dir / "detector" / "losses.png", "detector loss", 360))
    parts.append(_img(ctx, ctx.train_dir / "pose" / "log.png", "voxel network training", 420))
    parts.append(_img(ctx, ctx.train_dir / "baseline" / "log.png", "baseline training", 420))
    return parts


def _evaluation(ctx: DemoContext, ev: dict[str, Any], predicted: dict[str, Any]) -> list[str]:
    """Steps 5-6: the error tables, the error figures and the overlay frames."""
    parts = ["<h2>5-6. Prediction and evaluation</h2>"]
    if ev:
        rows = [[k, v["median"], v["p30"], v["p70"]] for k, v in ev["labels"].items()]
        parts.append(
            "<p>Held-out instants, cube on the true centre (<code>freipose eval</code>): "
            "voxel network (P0: 3D network, P1: refined) vs. triangulation baseline.</p>"
            + _table(["method", "median JPE mm", "30 %", "70 %"], rows)
        )
        rows = [[k, v["median"]] for k, v in ev["pipeline"].items()]
        parts.append(
            "<p>Whole pipeline (detector + voxel network) on every frame of each session "
            "against the true 3D keypoints:</p>" + _table(["session", "median JPE mm"], rows)
        )
    folder = ctx.out / "evaluation"
    parts.append(_img(ctx, folder / "labels" / "jpe_boxplot.png",
                      "per-keypoint errors, held-out instants", 700))  # fmt: skip
    parts.append(_img(ctx, folder / "labels" / "pck.png", "PCK", 360))
    parts.append(_img(ctx, folder / "pipeline" / "jpe_boxplot.png",
                      "per-keypoint errors, whole pipeline", 700))  # fmt: skip
    ov = predicted.get("overlay", {})
    if ov:
        parts.append(
            f"<p>Overlay clip: <a href='{html.escape(_rel(ctx, ov['clip']))}'>"
            f"{html.escape(_rel(ctx, ov['clip']))}</a> (frames below).</p>"
        )
        for f in ov["frames"]:
            parts.append(_img(ctx, Path(f), Path(f).stem, 1000))
    return parts


def _analysis_tables(a: dict[str, Any]) -> list[str]:
    """The classifier scores and the best single variables of one analysis."""
    rows = [
        [c["evaluated_on"], c["balanced_accuracy"], c["f1"], c["p_value"], c["n_effective"]]
        for c in a["classification"]
    ]
    top = [[t["variable"], t["f1"], t["p_value"], t["significant"]] for t in a["top_variables"]]
    n_top = int(round(a["top10_share_stimulated_part"] * 10))
    return [
        "<p>Linear SVM on all variables, trained on the train recording, scored on "
        "the test recording:</p>"
        + _table(["evaluated on", "balanced accuracy", "F1", "p", "n effective"], rows),
        f"<p>Best single variables ({n_top} of the top 10 belong to the stimulated "
        f"{STIM_PART}; {a['significant']} significant after the "
        "autocorrelation-corrected, Bonferroni-adjusted chi-squared test):</p>"
        + _table(["variable", "F1", "p", "significant"], top),
    ]


def _analysis(ctx: DemoContext, an: dict[str, Any]) -> list[str]:
    """Step 7: the analysis of the predicted poses and of the true keypoints."""
    parts = ["<h2>7. Analysis</h2>"]
    for key, label, sub in (
        ("predicted", "the predicted poses", "results"),
        ("truth", "the true keypoints (perfect tracking, for comparison)", "results_truth"),
    ):
        a = an.get(key)
        res_dir = ctx.out / "analysis" / sub
        parts.append(f"<h3>On {html.escape(label)}</h3>")
        if a:
            parts += _analysis_tables(a)
        for f in sorted(res_dir.glob("attribution_*.png")):
            parts.append(_img(ctx, f, f"attribution heat map ({key})", 1000))
        parts.append(_img(ctx, res_dir / "classifier_response.png",
                          f"onset dynamics ({key})", 480))  # fmt: skip
        for f in sorted(res_dir.glob("top_variables_*.png")):
            parts.append(_img(ctx, f, f"top variables around onset ({key})", 700))
    return parts


def run(ctx: DemoContext) -> dict[str, Any]:
    """Write ``report.html`` from the markers and figures of the finished steps.

    Args:
        ctx: the demo run.

    Returns:
        ``{"report": path}``.
    """
    m = {s: (read_marker(ctx.out, s) or {}) for s in STEPS}
    r = {s: m[s].get("results", {}) for s in STEPS}
    parts = _head(ctx, m)
    parts += _calibration(ctx, r["calibrate"])
    parts += _labels(r["labels"])
    parts += _training(ctx, r["train"])
    parts += _evaluation(ctx, r["evaluate"], r["predict"])
    parts += _analysis(ctx, r["analyze"])
    parts.append("</body></html>")
    path = ctx.out / "report.html"
    atomic_write_text(path, "\n".join(parts) + "\n")
    ctx.say(f"  wrote {path}")
    return {"report": str(path)}
