"""Step 8, ``report``: ``OUTDIR/report.html`` with every step's numbers and figures.

The page is rendered from the Jinja2 template ``templates/report.html.j2`` (its style is
inline, so it opens offline with nothing fetched). This module turns the step markers into
the template's plain values: sentences' numbers, tables with named columns and units, and
figures given by their path relative to the demo folder.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

from freipose import __version__
from freipose.analysis.config import AttributionConfig
from freipose.demo.context import DemoContext
from freipose.demo.markers import STEPS, read_marker
from freipose.demo.presets import SPLIT_ROLES, STIM_PART
from freipose.demo.steps.analyze import ranked, raw_vs_smoothed, significant_variables
from freipose.demo.steps.evaluate import lift_note
from freipose.io.atomic import atomic_write_text
from freipose.io.toml import read_toml

TEMPLATES = Path(__file__).parent / "templates"

# Human names and units of the synthetic stimulation settings (freipose.synth.stimulation).
_STIMULATION = {
    "body_part": ("stimulated body part", ""),
    "effect": ("effect", ""),
    "frequency_hz": ("oscillation frequency", "Hz"),
    "amplitude_mm": ("amplitude", "mm"),
    "duration_s": ("duration of each stimulation", "s"),
    "spacing_s": ("pause between stimulations", "s"),
    "onset_s": ("start of the first stimulation", "s"),
}

# The analyses of the demo: marker key, what they analysed, results folder under analysis/.
_ANALYSES = (
    ("predicted", "the predicted poses", "results"),
    ("smoothed", "the smoothed predicted poses (freipose smooth)", "results_smoothed"),
    ("truth", "the true keypoints (perfect tracking, for comparison)", "results_truth"),
)

_METHODS = {
    "voxel_P0": "voxel network, P0 (3D network output)",
    "voxel_P1": "voxel network, P1 (refined with the 2D views)",
    "baseline": "baseline (2D network per view, triangulated)",
}


def num(v: Any) -> str:
    """A table cell: floats with 3 significant digits (whole numbers from 1000 on), NaN as "-"."""
    if isinstance(v, bool) or not isinstance(v, float):
        return str(v)
    if not math.isfinite(v):
        return "-"
    return f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}"


def _figure(ctx: DemoContext, path: Path | str, caption: str, size: str = "full") -> dict[str, Any]:
    """A figure of the page: ``src`` relative to the demo folder, caption, CSS size class.

    ``size`` is ``"full"`` (page width), ``"half"`` or ``"third"`` (side by side).
    """
    p = Path(path)
    return {
        "src": Path(os.path.relpath(p, ctx.out)).as_posix(),
        "caption": caption,
        "size": size,
        "exists": p.is_file(),
    }


def _stimulation_rows(stim: dict[str, Any]) -> list[tuple[str, str]]:
    """The stimulation settings as (setting, value with unit) rows; unknown keys by name."""
    rows = []
    for key, value in stim.items():
        name, unit = _STIMULATION.get(key, (key.replace("_", " "), ""))
        text = num(float(value)) if isinstance(value, int | float) else str(value)
        rows.append((name, f"{text} {unit}".strip()))
    return rows


def _intro(ctx: DemoContext, markers: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The preset, the recordings, the stimulation settings and the step run times."""
    p = ctx.preset
    times = [(s, float(markers[s].get("seconds", float("nan")))) for s in STEPS if s != "report"]
    total = sum(t for _, t in times if math.isfinite(t))
    return {
        "preset": p.name,
        "version": __version__,
        "n_cameras": p.n_cameras,
        "size": p.size,
        "fps": num(float(p.fps)),
        "frames": p.session_frames,
        "seconds": num(p.session_frames / p.fps),
        "sessions": [(s.name, SPLIT_ROLES[s.split]) for s in p.sessions],
        "stim_part": STIM_PART,
        "stimulation": _stimulation_rows(dict(p.stimulation)),
        "times": [(s, num(t)) for s, t in times],
        "total_minutes": num(total / 60.0),
    }


def _calibration(ctx: DemoContext, cal: dict[str, Any]) -> dict[str, Any]:
    """Steps 1-2: the per-camera errors against the true rig and the calibration figures."""
    out: dict[str, Any] = {"summary": cal.get("summary"), "rows": [], "aspect_fixed": False}
    comp_path = ctx.out / "calibration" / "comparison.json"
    if comp_path.is_file():
        comp = json.loads(comp_path.read_text())
        focal = [tuple(float(x) for x in f) for f in comp["focal_percent"]]
        out["aspect_fixed"] = all(math.isclose(fx, fy, abs_tol=1e-9) for fx, fy in focal)
        out["scale"] = f"{comp['scale']:.4f}"
        for c, dc, rot, (fx, fy) in zip(
            comp["cameras"], comp["center_mm"], comp["rotation_deg"], focal
        ):
            row = [c, f"{dc:.2f}", f"{rot:.3f}", f"{fx:+.2f}"]
            out["rows"].append(row if out["aspect_fixed"] else [*row, f"{fy:+.2f}"])
    rep = ctx.out / "calibration" / "report"
    out["figures"] = [
        _figure(ctx, ctx.out / "calibration" / "comparison.png", "Errors of the calibrated "
                "rig against the true rig, per camera (after aligning the world frames)."),
        _figure(ctx, rep / "rig_3d.png", "The calibrated rig: camera positions and viewing "
                "directions (mm).", "half"),
    ]  # fmt: skip
    out["errors"] = [
        _figure(ctx, e, f"Reprojection errors of camera {e.stem[7:]} (px).", "third")
        for e in sorted(rep.glob("errors_*.png"))[:3]
    ]
    return out


def _eval_samples(ctx: DemoContext) -> int | None:
    """``schedule.eval_samples`` of the demo's training config (validation set size), or None."""
    path = ctx.train_dir / "config.toml"
    if not path.is_file():
        return None
    value = read_toml(path, "training config").get("schedule", {}).get("eval_samples")
    return int(value) if isinstance(value, int) else None


def _detector_rows(det: dict[str, Any]) -> list[tuple[str, str, str]]:
    """The detector's metrics as (quantity, value with unit, what it counts) rows."""
    rows = []
    if "recall" in det:
        rows.append(("boxes found (IoU at least 0.5 with the true box)",
                     f"{100 * det['recall']:.1f} %",
                     f"of {det.get('n_views', '?')} views showing the animal, boxes made "
                     "consistent across the views; the best box of each view alone: "
                     f"{100 * det.get('recall_top1', float('nan')):.1f} %"))  # fmt: skip
    if "center_rate" in det:
        agree = float(det.get("mean_agree", float("nan")))
        rows.append(("3D centre found", f"{100 * det['center_rate']:.1f} %",
                     f"of {det.get('n_instants', '?')} evaluation instants; "
                     f"{agree:.1f} views agree on average"))  # fmt: skip
    med = det.get("median_center_error", det.get("median_center_error_mm"))
    if med is not None:
        rows.append(("median 3D centre error", f"{num(float(med))} mm",
                     "distance of the detected centre from the true centre; the pose "
                     "network's cube is placed there"))  # fmt: skip
    if "cpu_fps" in det:
        rows.append(("speed", f"{num(float(det['cpu_fps']))} images/s",
                     "detector forward pass on this machine's CPU"))  # fmt: skip
    if "train_seconds" in det:
        rows.append(("training time", f"{num(float(det['train_seconds']))} s", ""))
    return rows


def _training(ctx: DemoContext, trained: dict[str, Any], ev: dict[str, Any]) -> dict[str, Any]:
    """Step 4: the detector's metrics, the training curves and the validation JPE."""
    last = trained.get("pose", {}).get("last_log", {})
    labels = ev.get("labels", {})
    val = None
    if last.get("val_jpe_p1") and "voxel_P1" in labels:
        val = {
            "p0": num(float(last["val_jpe_p0"])),
            "p1": num(float(last["val_jpe_p1"])),
            "eval_p0": num(float(labels["voxel_P0"]["median"])),
            "eval_p1": num(float(labels["voxel_P1"]["median"])),
            "samples": _eval_samples(ctx),
            "instants": ctx.preset.eval_instants,
        }
    t = ctx.train_dir
    return {
        "detector": _detector_rows(trained.get("detector", {}).get("metrics", {})),
        "val": val,
        "figures": [
            _figure(ctx, t / "pose" / "log.png", "Voxel network training: losses and the "
                    "validation JPE (mm) against the training step."),
            _figure(ctx, t / "baseline" / "log.png", "Baseline training: losses and the "
                    "validation JPE (mm) against the training step."),
            _figure(ctx, t / "detector" / "losses.png", "Detector training loss against "
                    "the training step.", "half"),
        ],
    }  # fmt: skip


def _failure_modes(ev: dict[str, Any]) -> dict[str, Any] | None:
    """The evaluate step's failure modes (symmetric pairs, bone lengths, warnings), or None."""
    fm = ev.get("failure_modes")
    if not fm:
        return None

    def mm(v: float | None) -> str:  # None: not measured (see freipose.nn.failure_modes)
        return "-" if v is None else num(float(v))

    pairs = [
        [f"{p['left']} / {p['right']}", mm(p["predicted_mm"]), mm(p["true_mm"]),
         p.get("missing") or f"{100 * float(p['swap_rate']):.1f} %",
         "yes" if p.get("collapsed") else "no"]
        for p in fm.get("pairs", [])
    ]  # fmt: skip
    bones = [[b["bone"], mm(b["predicted_mm"]), mm(b["true_mm"])] for b in fm.get("bones", [])]
    return {"pairs": pairs, "bones": bones, "warnings": list(fm.get("warnings", []))}


def _comparison_row(c: dict[str, Any]) -> list[str]:
    """One paired comparison (:mod:`freipose.nn.compare`) as table cells."""

    def diff(prefix: str) -> str:
        d, lo, hi = (float(c[f"{prefix}{k}"]) for k in ("difference", "low", "high"))
        return f"{d:+.2f} ({lo:+.2f} to {hi:+.2f}): {c[prefix + 'verdict']}"

    return [
        f"{_METHODS.get(c['a'], c['a'])} vs {_METHODS.get(c['b'], c['b'])}",
        diff(""),
        diff("mean_") if "mean_difference" in c else "-",
        f"{100 * float(c['win_rate']):.0f} %",
    ]


def _lift_notes(ev: dict[str, Any]) -> list[str]:
    """Per recording, a sentence where the predicted lift disagrees with the true one."""
    notes = [lift_note(k, v["stimulated_part"])
             for k, v in ev.get("pipeline", {}).items() if v.get("stimulated_part")]  # fmt: skip
    return [n for n in notes if n]


def _stimulated_rows(ev: dict[str, Any]) -> list[list[str]]:
    """Per recording: the stimulated keypoint's errors and lift, stimulated frames vs rest.

    Millimetres with one decimal as the demo prints them; heights and their changes signed.
    """

    def mm(v: Any, sign: str = "") -> str:
        return "-" if v is None or not math.isfinite(float(v)) else f"{float(v):{sign}.1f}"

    rows = []
    for k, v in ev.get("pipeline", {}).items():
        r = v.get("stimulated_part")
        if not r:
            continue
        st, rest = r["stimulated"], r["rest"]
        rows.append([k, mm(st["median_error_mm"]), mm(rest["median_error_mm"]),
                     mm(st["median_height_error_mm"], "+"), mm(rest["median_height_error_mm"], "+"),
                     mm(r.get("lift_pred_mm"), "+"), mm(r.get("lift_true_mm"), "+")])  # fmt: skip
    return rows


def _evaluation(ctx: DemoContext, ev: dict[str, Any]) -> dict[str, Any]:
    """Steps 5-6: the error tables and figures."""
    labels = [
        [_METHODS.get(k, k), num(float(v["median"])), num(float(v["p30"])), num(float(v["p70"]))]
        for k, v in ev.get("labels", {}).items()
    ]
    pipeline = [
        [k, num(float(v["median"])), str(v.get("missing", "-"))]
        for k, v in ev.get("pipeline", {}).items()
    ]
    refs = [[k, num(float(v["median_mm"]))] for k, v in ev.get("references", {}).items()]
    folder = ctx.out / "evaluation"
    return {
        "labels": labels,
        "pipeline": pipeline,
        "stimulated": _stimulated_rows(ev),
        "lift_notes": _lift_notes(ev),
        "references": refs,
        "comparisons": [_comparison_row(c) for c in ev.get("comparisons", [])],
        "failure_modes": _failure_modes(ev),
        "instants": ctx.preset.eval_instants,
        "figures": [
            _figure(ctx, folder / "labels" / "jpe_boxplot.png", "Error per keypoint on the "
                    "held-out instants (mm; boxes: quartiles, whiskers: 1.5 IQR)."),
            _figure(ctx, folder / "labels" / "pck.png", "Share of keypoints within a "
                    "distance of the truth (PCK) on the held-out instants.", "half"),
            _figure(ctx, folder / "pipeline" / "jpe_boxplot.png", "Error per keypoint of "
                    "the whole pipeline on every frame (mm)."),
        ],
    }  # fmt: skip


def _overlay(ctx: DemoContext, predicted: dict[str, Any]) -> dict[str, Any]:
    """Step 5's overlay clip and its still frames, when present."""
    ov = predicted.get("overlay", {})
    span = None
    if "start_s" in ov:
        windows = [(f"{a:.1f}", f"{b:.1f}") for a, b in ov["stimulation_s"]]
        span = {
            "start": f"{ov['start_s']:.1f}",
            "end": f"{ov['end_s']:.1f}",
            "stimulation": windows,
        }
    return {
        "span": span,
        "video": _figure(ctx, ov["clip"], "") if ov.get("clip") else None,
        "frames": [
            _figure(ctx, f, f"Frame {int(Path(f).stem.rsplit('frame', 1)[-1])} of the test "
                    "recording.") for f in ov.get("frames", [])
        ],
    }  # fmt: skip


def _smoothing(ctx: DemoContext, an: dict[str, Any]) -> dict[str, Any] | None:
    """The analysis of the raw and the smoothed predictions side by side, and the figure.

    The rows are :func:`~freipose.demo.steps.analyze.raw_vs_smoothed`'s, the text the
    demo prints; None when the smoothed predictions were not analysed.
    """
    smooth = an.get("smooth", {})
    if not (an.get("predicted") and an.get("smoothed")):
        return None
    test = ctx.preset.with_split("test")[0].name
    caption = (f"The stimulated {STIM_PART}, the nose and the tail on the test day "
               f"({test}): height above the floor (z, mm) of the raw prediction (dots), the "
               "smoothed one (line, band: 2 standard deviations) and the truth (dashed); "
               "grey: stimulation.")  # fmt: skip
    return {
        "rows": [list(r) for r in raw_vs_smoothed(an["predicted"], an["smoothed"])],
        "figure": _figure(ctx, smooth["figure"], caption) if smooth.get("figure") else None,
    }


def _significant(a: dict[str, Any], res_dir: Path) -> list[dict[str, Any]]:
    """The significant single variables of an analysis, from its marker or its results.

    A marker written without the list (an older demo folder) gets it from the analysis's
    ``attribution.csv``.
    """
    if "significant_variables" in a:
        return list(a["significant_variables"])
    csv = res_dir / "attribution.csv"
    if not a.get("significant") or not csv.is_file():
        return []
    import pandas as pd

    return significant_variables(ranked(pd.read_csv(csv)))


def _analysis_one(ctx: DemoContext, a: dict[str, Any] | None, sub: str) -> dict[str, Any]:
    """The classifier scores, the best single variables and the figures of one analysis."""
    splits = {s.split: s.name for s in ctx.preset.sessions}
    res_dir = ctx.out / "analysis" / sub
    out: dict[str, Any] = {"classification": [], "top": [], "figures": [], "truth_notes": []}
    if a:
        for c in a["classification"]:
            out["classification"].append([
                f"{splits.get('train', c['animal'])} (train day)",
                f"{splits.get('test', c['evaluated_on'])} (test day)",
                num(float(c["balanced_accuracy"])), num(float(c["f1"])),
                num(float(c["p_value"])), num(float(c["n_effective"])),
                num(float(c.get("train_balanced_accuracy", float("nan")))),
            ])  # fmt: skip
        for t in a["top_variables"]:
            out["top"].append([
                t["variable"], num(float(t["f1"])), num(float(t["p_value"])),
                num(float(t.get("p_adjusted", float("nan")))),
                "yes" if t["significant"] else "no",
            ])  # fmt: skip
        out["n_top"] = int(round(a["top10_share_stimulated_part"] * 10))
        out["significant"] = a["significant"]
        out["significant_variables"] = [
            [v["variable"], str(v["rank"]), num(float(v["f1"])), num(float(v["p_value"])),
             num(float(v["p_adjusted"]))] for v in _significant(a, res_dir)
        ]  # fmt: skip
        out["n_variables"] = a["classification"][0].get("n_variables_used", "all")
        out["truth_notes"] = list(a.get("truth_notes", []))
    heat = (
        "F-score of each single variable by body part (rows) and variable (columns); white: "
        "not tested (the variable is constant over the training frames or undefined)."
    )
    top = "The best single variables around stimulation onset (z-scored; mean and SEM)."
    for f in sorted(res_dir.glob("attribution_*.png")):
        out["figures"].append(_figure(ctx, f, heat))
    for f in sorted(res_dir.glob("top_variables_*.png")):
        out["figures"].append(_figure(ctx, f, top))
    out["figures"].append(_figure(ctx, res_dir / "classifier_response.png", "The full "
                                  "classifier's mean prediction around stimulation onset.",
                                  "half"))  # fmt: skip
    return out


def context(ctx: DemoContext) -> dict[str, Any]:
    """The template's values, read from the markers and figures of the finished steps."""
    m = {s: (read_marker(ctx.out, s) or {}) for s in STEPS}
    r = {s: m[s].get("results", {}) for s in STEPS}
    an = r["analyze"]
    return {
        "intro": _intro(ctx, m),
        "calibration": _calibration(ctx, r["calibrate"]) if r["calibrate"] else None,
        "labels": r["labels"] or None,
        "training": _training(ctx, r["train"], r["evaluate"]) if r["train"] else None,
        "evaluation": _evaluation(ctx, r["evaluate"]) if r["evaluate"] else None,
        "overlay": _overlay(ctx, r["predict"]),
        "smoothing": _smoothing(ctx, an),
        "analysis": [
            (label, _analysis_one(ctx, an.get(key), sub))
            for key, label, sub in _ANALYSES
            if an.get(key) or (ctx.out / "analysis" / sub).is_dir()
        ],
        "stim_part": STIM_PART,
        "alpha": num(AttributionConfig(**ctx.preset.analysis).alpha),
    }


def render_html(values: dict[str, Any]) -> str:
    """The report page from the template and :func:`context`'s values."""
    import jinja2

    env = jinja2.Environment(
        loader=jinja2.FileSystemLoader(TEMPLATES),
        autoescape=True,
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    return env.get_template("report.html.j2").render(**values)


def run(ctx: DemoContext) -> dict[str, Any]:
    """Write ``report.html`` from the markers and figures of the finished steps.

    Args:
        ctx: the demo run.

    Returns:
        ``{"report": path}``.
    """
    path = ctx.out / "report.html"
    atomic_write_text(path, render_html(context(ctx)))
    ctx.say(f"  wrote {path}")
    return {"report": str(path)}
