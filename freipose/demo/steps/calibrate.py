"""Step 2, ``calibrate``: calibrate the cameras from the board videos and compare with the truth."""

from __future__ import annotations

import json
import os
from typing import TYPE_CHECKING, Any

import numpy as np

from freipose.demo.context import DemoContext, save_png
from freipose.geometry.alignment import rig_errors as geometry_rig_errors
from freipose.io.atomic import atomic_write_text

if TYPE_CHECKING:
    from pathlib import Path

    from freipose.geometry.camera import CameraRig


def rig_errors(est: CameraRig, truth: CameraRig) -> dict[str, Any]:
    """Per-camera errors of a calibrated rig against the truth, after aligning the world frames.

    The calibrated world (board on the floor in frame 0) differs from the true one by a
    rigid motion; it is estimated from the camera centres (a similarity, so the scale error
    shows too).

    Args:
        est: the calibrated rig.
        truth: the true rig (same camera order).

    Returns:
        ``cameras`` (names), ``center_mm`` (V,) centre errors, ``rotation_deg`` (V,) rotation
        errors, ``focal_percent`` (V, 2) focal length errors (fx and fy), the alignment
        ``scale``, ``R`` (3, 3) and ``t`` (3,) mapping calibrated to true world coordinates,
        all as JSON-compatible lists and floats.
    """
    names = [c.name for c in truth]
    dc, rot, fe, (s, R, t) = geometry_rig_errors(est, truth)
    return {
        "cameras": names,
        "center_mm": dc.tolist(),
        "rotation_deg": rot.tolist(),
        "focal_percent": fe.tolist(),
        "scale": s,
        "R": R.tolist(),
        "t": t.tolist(),
    }


def _plot_comparison(err: dict[str, Any], path: Path) -> None:
    """Bar charts of the centre, rotation and focal length errors per camera."""
    from freipose.io.figures import new_figure

    fig = new_figure(figsize=(11, 3.4), layout="constrained")
    axes = fig.subplots(1, 3)
    x = np.arange(len(err["cameras"]))
    for ax, vals, title in (
        (axes[0], err["center_mm"], "camera centre error (mm)"),
        (axes[1], err["rotation_deg"], "rotation error (deg)"),
        (axes[2], [abs(f[0]) for f in err["focal_percent"]], "|focal length error| (%)"),
    ):
        ax.bar(x, vals, color="C0")
        ax.set_xticks(x)
        ax.set_xticklabels(err["cameras"], rotation=45, fontsize=8)
        ax.set_title(title, fontsize=9)
        ax.grid(axis="y", alpha=0.3)
    fig.suptitle("Calibration vs. the true rig (after aligning the world frames)", fontsize=10)
    save_png(fig, path)


def run(ctx: DemoContext) -> dict[str, Any]:
    """Calibrate the rig (``calibration/calibration.toml``) and compare it with the true rig.

    Writes the calibration report, ``comparison.json`` (:func:`rig_errors`) and
    ``comparison.png`` next to the calibration.

    Args:
        ctx: the demo run.

    Returns:
        ``summary`` (largest errors, RMS, scale) and ``alignment`` (``scale``, ``R``, ``t``:
        calibrated to true world coordinates).
    """
    from freipose.calibration.board_files import load_board
    from freipose.calibration.options import CalibrationOptions
    from freipose.calibration.pipeline import calibrate
    from freipose.calibration.report import write_report
    from freipose.io.calibration import load_calibration, save_calibration
    from freipose.io.video import find_camera_videos

    folder = ctx.calib_videos
    videos = find_camera_videos(folder)
    board = load_board(folder / "board.toml")
    truth = load_calibration(folder / "true_calibration.toml")
    out = ctx.calibration
    out.parent.mkdir(parents=True, exist_ok=True)
    opts = CalibrationOptions(origin_frame=0, jobs=min(2, os.cpu_count() or 1), progress=False)
    result = calibrate([videos[n] for n in truth.names], board, out, opts)
    save_calibration(result.rig, out)
    write_report(result, out.parent / "report")
    err = rig_errors(result.rig, truth)
    atomic_write_text(out.parent / "comparison.json", json.dumps(err, indent=2) + "\n")
    for name, dc, rot, fe, st in zip(
        err["cameras"], err["center_mm"], err["rotation_deg"], err["focal_percent"], result.stats
    ):
        ctx.say(
            f"  {name}: reprojection RMS {st.rms:.2f} px, centre error {dc:.2f} mm, "
            f"rotation error {rot:.3f} deg, focal error {fe[0]:+.2f} %"
        )
    _plot_comparison(err, out.parent / "comparison.png")
    summary = {
        "max_center_mm": float(np.max(err["center_mm"])),
        "max_rotation_deg": float(np.max(err["rotation_deg"])),
        "max_focal_percent": float(np.max(np.abs(err["focal_percent"]))),
        "max_rms_px": float(np.nanmax([s.rms for s in result.stats])),
        "scale": err["scale"],
    }
    ctx.say(
        f"  largest errors: centre {summary['max_center_mm']:.2f} mm, rotation "
        f"{summary['max_rotation_deg']:.3f} deg, focal {summary['max_focal_percent']:.2f} %; "
        f"scale {summary['scale']:.4f}"
    )
    return {"summary": summary, "alignment": {k: err[k] for k in ("scale", "R", "t")}}
