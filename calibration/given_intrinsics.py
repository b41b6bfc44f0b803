"""Whether intrinsics given from another recording explain this recording's detections.

A camera whose intrinsics were given (``--fix-intrinsics``, ``--intrinsics-from``) keeps them
in the bundle adjustment; if they belong to another lens, focus or resolution the camera's
detections are explained only with a systematic error, which per-camera outlier rejection
takes for detection noise. The evidence is a second adjustment in which those cameras'
focal lengths, principal points and radial distortion (k1 k2) are free: when it explains a
camera's own detections at less than 1 / :data:`MAX_ERROR_RATIO` of the given model's
median error, the given intrinsics are refused.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from freipose.calibration.bundle import BundleResult
from freipose.calibration.options import CalibrationOptions
from freipose.calibration.params import DIST, PINHOLE

__all__ = ["MAX_ERROR_RATIO", "given_intrinsics_errors"]

# the given intrinsics' median error may be this many times a free fit's
MAX_ERROR_RATIO = 1.5


def given_intrinsics_errors(
    names: Sequence[str],
    ba: BundleResult,
    free: np.ndarray,
    square: np.ndarray,
    fixed: frozenset[str],
    opt: CalibrationOptions,
) -> dict[str, tuple[float, float]]:
    """The given-intrinsics cameras that a free fit explains much better.

    Args:
        names: the camera names, in rig order.
        ba: the final bundle adjustment (with the given intrinsics held).
        free: (C, 15) bool, its free parameters.
        square: (C,) bool, its cameras with fy tied to fx.
        fixed: the cameras whose intrinsics were given.
        opt: the calibration's options (loss, rejection, solver).

    Returns:
        per such camera, its median inlier error (px) with the given intrinsics and with
        intrinsics fitted to this recording (only cameras where the ratio exceeds
        :data:`MAX_ERROR_RATIO`).
    """
    from freipose.calibration.stages import run_bundle

    idx = [i for i, n in enumerate(names) if n in fixed]
    if not idx:
        return {}
    opened = free.copy()
    for i in idx:
        opened[i, PINHOLE] = True
        opened[i, DIST] = [True, True, False, False, False]
    tie = square.copy()
    tie[idx] = False
    refit = run_bundle(
        ba.cam_params, opened, ba.frame_params, ba.frames, ba.obs, opt, ba.f_scale, tie, ba
    )
    out = {}
    for i in idx:
        mine = ba.obs.cam == i
        given = float(np.median(ba.errors[mine & ba.inliers]))
        fitted = float(np.median(refit.errors[mine & refit.inliers]))
        if given > MAX_ERROR_RATIO * fitted:
            out[names[i]] = (given, fitted)
    return out
