"""Per-camera result figures of a calibration and the warnings they give rise to."""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from freipose.calibration.bundle import BundleResult
from freipose.calibration.bundle_problem import Observations
from freipose.calibration.detect import CameraDetections
from freipose.calibration.intrinsics import IntrinsicsResult

logger = logging.getLogger(__name__)

__all__ = [
    "HIGH_ERROR_PX",
    "CameraStats",
    "bundle_stats",
    "high_error_warnings",
    "intrinsic_standard_errors",
    "intrinsics_stats",
]

# the intrinsic parameters of a camera row (freipose.calibration.params), in order
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")

HIGH_ERROR_PX = 1.0


@dataclass(frozen=True)
class CameraStats:
    """Per-camera result figures (px)."""

    name: str
    frames_detected: int
    points_detected: int
    points_used: int
    rms: float
    median: float
    intrinsics_frames: int

    def to_dict(self) -> dict[str, Any]:
        """The figures as ``summary.json`` holds them (rounded; ``None`` where undefined)."""
        return {
            "frames_with_detections": self.frames_detected,
            "points_detected": self.points_detected,
            "points_used": self.points_used,
            "reprojection_rms_px": round(self.rms, 4) if np.isfinite(self.rms) else None,
            "reprojection_median_px": round(self.median, 4) if np.isfinite(self.median) else None,
            "intrinsics_frames": self.intrinsics_frames,
        }


def intrinsics_stats(
    dets: Sequence[CameraDetections], intr: Mapping[str, IntrinsicsResult]
) -> list[CameraStats]:
    """Figures of an intrinsics-only calibration (errors of the intrinsics calibration).

    Args:
        dets: per camera, the detections.
        intr: per calibrated camera, the intrinsics result.

    Returns:
        one entry per camera, in detection order.
    """
    stats = []
    for d in dets:
        r = intr.get(d.name)
        stats.append(
            CameraStats(
                d.name,
                int((d.counts > 0).sum()),
                int(d.mask.sum()),
                int(sum(d.mask[f].sum() for f in r.frames)) if r else 0,
                r.rms if r else float("nan"),
                float("nan"),
                len(r.frames) if r else 0,
            )
        )
    return stats


def bundle_stats(
    dets: Sequence[CameraDetections],
    ba: BundleResult,
    obs: Observations,
    intr: Mapping[str, IntrinsicsResult],
) -> list[CameraStats]:
    """Figures of the final bundle adjustment (errors of the inlier detections).

    Args:
        dets: per camera, the detections.
        ba: the final bundle adjustment.
        obs: the observations it ran on.
        intr: per calibrated camera, the intrinsics result.

    Returns:
        one entry per camera, in detection order.
    """
    stats = []
    for i, d in enumerate(dets):
        m = obs.cam == i
        e = ba.errors[m & ba.inliers]
        r = intr.get(d.name)
        stats.append(
            CameraStats(
                d.name,
                int((d.counts > 0).sum()),
                int(d.mask.sum()),
                int(e.size),
                float(np.sqrt(np.mean(e**2))) if e.size else float("nan"),
                float(np.median(e)) if e.size else float("nan"),
                len(r.frames) if r else 0,
            )
        )
    return stats


def high_error_warnings(stats: Sequence[CameraStats]) -> list[str]:
    """Log and return a warning for every camera whose RMS error is above :data:`HIGH_ERROR_PX`.

    Args:
        stats: the cameras' figures.

    Returns:
        the warnings, in camera order.
    """
    warnings = []
    for s in stats:
        if np.isfinite(s.rms) and s.rms > HIGH_ERROR_PX:
            msg = (
                f"camera {s.name}: reprojection RMS {s.rms:.2f} px is above "
                f"{HIGH_ERROR_PX:.0f} px; "
                f"check focus and motion blur, the board's flatness and dimensions, or "
                f"try --dist-model full"
            )
            logger.warning(msg)
            warnings.append(msg)
    return warnings


def intrinsic_standard_errors(
    cov: np.ndarray, free: np.ndarray, square: np.ndarray, names: Sequence[str]
) -> dict[str, dict[str, float]]:
    """Standard errors of every camera's free intrinsics.

    Args:
        cov: (C, 15, 15) the cameras' parameter covariances
            (:func:`freipose.calibration.bundle.camera_covariance`).
        free: (C, 15) bool, the free parameters.
        square: (C,) bool, cameras whose fy is tied to fx (fy gets fx's error).
        names: the camera names, in rig order.

    Returns:
        ``{camera: {"fx": se, "fy": se, "cx": ...}}`` (px for focal length and principal
        point); only free parameters appear, and a camera with none has an empty entry.
    """
    out: dict[str, dict[str, float]] = {}
    for c, name in enumerate(names):
        se = {}
        for j, key in enumerate(INTRINSIC_NAMES):
            tied = key == "fy" and bool(square[c]) and bool(free[c, 0])
            if free[c, j] or tied:
                v = cov[c, 0, 0] if tied else cov[c, j, j]
                se[key] = float(np.sqrt(max(float(v), 0.0)))
        out[name] = se
    return out
