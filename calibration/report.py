"""Calibration report: ``summary.json``, ``report.txt`` and figures (errors, coverage, 3D rig)."""

from __future__ import annotations

import json
import logging
import textwrap
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from freipose.calibration.coverage import FLOOR_NEAR_MM, CameraCoverage
from freipose.calibration.detect import CameraDetections
from freipose.calibration.pipeline import CalibrationResult
from freipose.calibration.plausibility import fold_pixel_radius
from freipose.io.figures import new_figure, save_figure

logger = logging.getLogger(__name__)

__all__ = ["report_text", "summary_dict", "write_report"]


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
        cov = {c.name: c for c in result.coverage}.get(s.name)
        if cov is not None:
            d["coverage"] = cov.to_dict()
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


def _board_words(board: Any) -> str:
    """The board in words, saying whether it is printed inverted."""
    d = dict(board.to_dict())
    kind = d.pop("type", "board")
    inverted = bool(d.pop("inverted", False))
    fields = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in d.items())
    ink = "printed inverted (white pattern on black)" if inverted else "printed normally"
    return f"{kind} ({fields}), {ink}"


def _camera_words(result: CalibrationResult, i: int) -> list[str]:
    """The lines of report.txt for camera ``i``."""
    s, det, cam = result.stats[i], result.detections[i], result.rig[i]
    back = det.back_views
    lines = [
        f"{s.name}: {s.frames_detected} frames with the board, {back} of them seen from behind "
        f"(found in the mirror image); {s.points_used} of {s.points_detected} corners used; "
        f"reprojection RMS {s.rms:.3f} px, median {s.median:.3f} px",
        f"  focal length {cam.K[0, 0]:.1f} px, principal point ({cam.K[0, 2]:.1f}, "
        f"{cam.K[1, 2]:.1f}) px, distortion {', '.join(f'{x:.4g}' for x in cam.dist)}",
    ]
    se = result.standard_errors.get(s.name)
    if se:
        lines.append("  standard errors: " + ", ".join(f"{k} {v:.3g}" for k, v in se.items()))
    cov = result.coverage[i] if i < len(result.coverage) else None
    if cov is not None:
        words = _coverage_text(cov)
        lines.append(
            f"  coverage: corners in {100 * cov.image_fraction:.0f} % of the image cells"
            + (f"; {words}" if words else "")
        )
    return lines


def report_text(result: CalibrationResult) -> str:
    """``report.txt``: the calibration in words (board, cameras, warnings, refusal findings).

    Args:
        result: the calibration.

    Returns:
        the text, one fact per line.
    """
    lines = [
        "FreiPose calibration report",
        f"board: {_board_words(result.board)}",
        f"world frame: {result.world}",
    ]
    up = result.rig.metadata.get("up")
    if up is not None:
        lines.append(f"up direction: {up} ({result.rig.metadata.get('up_source', '')})")
    lines.append("")
    for i in range(len(result.stats)):
        lines += _camera_words(result, i)
    if result.warnings:
        lines += ["", "Warnings:", *(f"- {w}" for w in result.warnings)]
    lines.append("")
    if result.findings:
        lines += [
            "SUSPECT: this calibration failed the plausibility checks and was written only "
            "because --force was given:",
            *(f"- {f.message}" for f in result.findings),
        ]
    else:
        lines.append(
            "Plausibility checks passed (field of view, principal point, distortion, board "
            "poses, rejected detections, focal-length standard error); a calibration that "
            "fails them is refused unless --force is given."
        )
    return "\n".join(lines) + "\n"


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


def _coverage_text(cov: CameraCoverage | None) -> str:
    """The second title line of a coverage map: depths and floor."""
    if cov is None:
        return ""
    parts = []
    if cov.depth_mm is not None:
        parts.append(f"board {cov.depth_mm[0]:.0f}-{cov.depth_mm[2]:.0f} mm away (5-95 %)")
    if cov.floor_views is not None:
        parts.append(f"{cov.floor_views} views within {FLOOR_NEAR_MM:.0f} mm of the floor")
    if cov.floor_region is not None:
        parts.append(f"floor region {100 * cov.floor_region:.0f} % covered")
    return "; ".join(parts)


def _coverage_map(
    det: CameraDetections,
    cov: CameraCoverage | None = None,
    fold: tuple[float, float, float] | None = None,
) -> Figure:
    """Where in the image a camera's corners were detected, per grid cell, and the floor.

    The cells of the coverage grid show their corner counts (empty cells grey); the floor
    that two cameras see is marked with red crosses when the floor is known; ``fold``
    ``(cx, cy, radius)`` (px) draws the circle beyond which the lens model folds.
    """
    w, h = det.size
    pts = det.points[det.mask]
    fig = new_figure(figsize=(6, 6 * h / max(w, 1) + 1.0), layout="constrained")
    ax = fig.subplots()
    grid = cov.grid if cov is not None else None
    if grid is not None:
        shown = np.ma.masked_equal(grid.astype(float), 0)
        ax.set_facecolor("0.8")  # cells without corners
        im = ax.imshow(shown, extent=(-0.5, w - 0.5, h - 0.5, -0.5), cmap="viridis",
                       interpolation="nearest", alpha=0.85)  # fmt: skip
        fig.colorbar(im, ax=ax, shrink=0.8, label="detected corners per cell")
        rows, cols = grid.shape
        for r in range(rows):
            for c in range(cols):
                ax.text((c + 0.5) * w / cols, (r + 0.5) * h / rows, str(grid[r, c]),
                        ha="center", va="center", fontsize=7, color="w")  # fmt: skip
    if len(pts):
        ax.scatter(pts[:, 0], pts[:, 1], s=0.5, c="k", alpha=0.3, linewidths=0)
    if cov is not None and cov.floor_pixels is not None and len(cov.floor_pixels):
        f = cov.floor_pixels
        ax.scatter(f[:, 0], f[:, 1], s=4, c="r", marker="+", linewidths=0.6,
                   label="floor seen by 2+ cameras")  # fmt: skip
    if fold is not None:
        t = np.linspace(0.0, 2 * np.pi, 181)
        ax.plot(fold[0] + fold[2] * np.cos(t), fold[1] + fold[2] * np.sin(t), "--", c="m",
                lw=1.2, label="the lens model folds beyond")  # fmt: skip
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="lower right", fontsize=7)
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    sub = _coverage_text(cov)
    ax.set_xlabel("x (px)" + ("\n" + textwrap.fill(sub, 80) if sub else ""), fontsize=8)
    ax.set_ylabel("y (px)", fontsize=8)
    head = f"{det.name}: {len(pts)} detected corners"
    if cov is not None:
        head += f" in {100 * cov.image_fraction:.0f} % of the image cells (grey: none)"
    ax.set_title(head, fontsize=9)
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
        tip = o - 0.6 * z  # the name behind the camera, clear of its marker and axis
        ax.text(*tip, cam.name, fontsize=8, ha="center", va="center")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    lims = np.array([ax.get_xlim(), ax.get_ylim(), ax.get_zlim()])
    mid, half = lims.mean(axis=1), max(float(np.ptp(lims, axis=1).max()) / 2, 1.0)
    ax.set_xlim(mid[0] - half, mid[0] + half)  # one scale on every axis
    ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_zlim(mid[2] - half, mid[2] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.set_title("cameras (red, optical axis) and board poses")
    if result.findings:
        cams = ", ".join(dict.fromkeys(f.camera for f in result.findings))
        fig.suptitle(f"SUSPECT calibration (written with --force): {cams}", color="r")
    return fig


def _fold_circle(result: CalibrationResult, i: int) -> tuple[float, float, float] | None:
    """(cx, cy, radius) px of camera ``i``'s lens-model fold inside its image, else None."""
    if i >= len(result.rig):
        return None
    cam = result.rig[i]
    r = fold_pixel_radius(cam.K, cam.dist, tuple(cam.size))
    return None if r is None else (float(cam.K[0, 2]), float(cam.K[1, 2]), r)


def write_report(result: CalibrationResult, outdir: str | Path) -> list[Path]:
    """Write the report: summary.json, report.txt and the figures.

    The figures: ``errors_<cam>.png``, ``coverage_<cam>.png`` per camera and ``rig_3d.png``.

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
    p = out / "report.txt"
    atomic_write_text(p, report_text(result))
    paths.append(p)
    for i, det in enumerate(result.detections):
        if result.bundle is not None:
            fig = _error_histogram(result, i, det.name)
            paths.append(save_figure(fig, out / f"errors_{det.name}.png", dpi=80))
        cov = result.coverage[i] if i < len(result.coverage) else None
        fig = _coverage_map(det, cov, _fold_circle(result, i))
        paths.append(save_figure(fig, out / f"coverage_{det.name}.png", dpi=80))
    paths.append(save_figure(_rig_figure(result), out / "rig_3d.png", dpi=80))
    return paths
