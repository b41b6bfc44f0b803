"""Calibration report: ``summary.json`` and figures (error histograms, coverage maps, 3D rig)."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from freipose.calibration.detect import CameraDetections
from freipose.calibration.pipeline import CalibrationResult
from freipose.io.figures import new_figure, save_figure

logger = logging.getLogger(__name__)

__all__ = ["summary_dict", "write_report"]


def summary_dict(result: CalibrationResult) -> dict[str, Any]:
    """The content of ``summary.json``.

    Args:
        result: the calibration.

    Returns:
        the board, frame count, per-camera figures (with ``back_side_views``, the frames
        in which the camera saw the board from behind), parameters and intrinsic standard
        errors, world frame, camera graph, warnings, the plausibility findings of a
        calibration written with ``--force`` (``suspect``, empty when plausible) and the
        bundle adjustment's statistics.
    """
    cams = {}
    back = {det.name: det.back_views for det in result.detections}
    for s, cam in zip(result.stats, result.rig):
        d = s.to_dict()
        d["back_side_views"] = int(back.get(s.name, 0))
        d["size"] = [int(cam.size[0]), int(cam.size[1])]
        d["focal_px"] = [round(float(cam.K[0, 0]), 3), round(float(cam.K[1, 1]), 3)]
        d["principal_point_px"] = [round(float(cam.K[0, 2]), 3), round(float(cam.K[1, 2]), 3)]
        d["distortion"] = [round(float(x), 6) for x in cam.dist]
        d["center_mm"] = [round(float(x), 3) for x in cam.center]
        se = result.standard_errors.get(s.name)
        if se:
            d["intrinsics_standard_errors"] = {k: float(f"{v:.4g}") for k, v in se.items()}
        cams[s.name] = d
    out: dict[str, Any] = {
        "board": result.board.to_dict(),
        "frames": int(result.detections[0].num_frames) if result.detections else 0,
        "cameras": cams,
        "world": result.world,
        "camera_graph": result.graph.to_dict() if result.graph is not None else None,
        "warnings": list(result.warnings),
        "suspect": [f.to_dict() for f in result.findings],
    }
    if result.bundle is not None:
        b = result.bundle
        e = b.errors[b.inliers]
        out["bundle_adjustment"] = {
            "initial_rms_px": round(b.initial_rms, 4),
            "final_rms_px": round(float(np.sqrt(np.mean(e**2))), 4) if e.size else None,
            "detections_used": int(b.inliers.sum()),
            "detections_rejected": int((~b.inliers).sum()),
            "board_poses": int(len(b.frames)),
            "rounds": b.rounds,
            "evaluations": b.nfev,
            "seconds": round(b.seconds, 3),
        }
    return out


def _error_histogram(result: CalibrationResult, i: int, name: str) -> Figure:
    """Histogram of camera ``i``'s reprojection errors after the bundle adjustment."""
    e = result.camera_errors(i)
    fig = new_figure(figsize=(5, 3.5))
    ax = fig.subplots()
    if e.size:
        bins = np.linspace(0, max(2.0, float(np.percentile(e, 99.5))), 40)
        ax.hist(e, bins=list(bins))
        ax.axvline(float(np.sqrt(np.mean(e**2))), color="r", label="RMS")
        ax.legend()
    ax.set_xlabel("reprojection error (px)")
    ax.set_ylabel("detections")
    ax.set_title(f"{name}: reprojection errors after bundle adjustment")
    fig.tight_layout()
    return fig


def _coverage_map(det: CameraDetections) -> Figure:
    """Where in the image a camera's corners were detected (2D histogram)."""
    w, h = det.size
    pts = det.points[det.mask]
    fig = new_figure(figsize=(5, 5 * h / max(w, 1) + 0.6))
    ax = fig.subplots()
    if len(pts):
        H, _xe, _ye = np.histogram2d(
            pts[:, 0], pts[:, 1], bins=(32, max(1, int(32 * h / w))), range=[[0, w], [0, h]]
        )
        ax.imshow(H.T, extent=(0, w, h, 0), cmap="viridis", interpolation="nearest")
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_title(f"{det.name}: detected corners ({len(pts)}) over the image")
    fig.tight_layout()
    return fig


def _rig_figure(result: CalibrationResult) -> Figure:
    """The cameras (centres and optical axes) and the board centres in 3D."""
    fig = new_figure(figsize=(6, 6))
    ax = fig.add_subplot(projection="3d")
    B = result.board_poses
    ok = np.isfinite(B[:, 0, 0])
    if ok.any():
        c = B[ok][:, :3, :3] @ np.append(np.mean(result.board.object_points[:, :2], 0), 0)
        c = c + B[ok][:, :3, 3]
        ax.scatter(c[:, 0], c[:, 1], c[:, 2], s=3, c="gray", label="board centres")
    centers = result.rig.centers
    scale = float(np.ptp(centers, axis=0).max()) * 0.1 if len(centers) > 1 else 100.0
    for cam in result.rig:
        o = cam.center
        z = cam.R[2] * max(scale, 50.0)
        ax.plot([o[0], o[0] + z[0]], [o[1], o[1] + z[1]], [o[2], o[2] + z[2]], "r-")
        ax.scatter(*o, c="r", s=20)
        ax.text(*o, cam.name, fontsize=8)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    ax.set_title("cameras (red, optical axis) and board poses")
    if result.findings:
        cams = ", ".join(dict.fromkeys(f.camera for f in result.findings))
        fig.suptitle(f"SUSPECT calibration (written with --force): {cams}", color="r")
    return fig


def write_report(result: CalibrationResult, outdir: str | Path) -> list[Path]:
    """Write ``summary.json``, ``errors_<cam>.png``, ``coverage_<cam>.png`` and ``rig_3d.png``.

    Args:
        result: the calibration.
        outdir: the report folder (made when missing).

    Returns:
        the written paths.
    """
    from freipose.io.atomic import atomic_write_text

    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    p = out / "summary.json"
    atomic_write_text(p, json.dumps(summary_dict(result), indent=2) + "\n")
    paths.append(p)
    for i, det in enumerate(result.detections):
        if result.bundle is not None:
            fig = _error_histogram(result, i, det.name)
            paths.append(save_figure(fig, out / f"errors_{det.name}.png", dpi=80))
        paths.append(save_figure(_coverage_map(det), out / f"coverage_{det.name}.png", dpi=80))
    paths.append(save_figure(_rig_figure(result), out / "rig_3d.png", dpi=80))
    return paths
