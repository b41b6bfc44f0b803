"""Model selection: keep only the intrinsic parameters the data support.

A camera keeps a principal-point offset, tangential distortion or fx != fy only when the
bundle adjustment's estimate differs from zero by more than a Wald chi-square at 1 %
significance.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from freipose.calibration.bundle import BundleResult, camera_covariance
from freipose.calibration.bundle_problem import Observations
from freipose.calibration.detect import CameraDetections
from freipose.calibration.options import CalibrationOptions
from freipose.calibration.params import DIST, FOCAL, PRINCIPAL, TANGENTIAL
from freipose.calibration.stages import run_bundle

logger = logging.getLogger(__name__)

__all__ = ["CHI2_1DOF_1PCT", "CHI2_2DOF_1PCT", "ModelSelection", "describe_model", "select_models"]

# Wald chi-square thresholds at 1 % significance: 2 degrees of freedom (principal point,
# tangential distortion) and 1 degree of freedom (fx = fy)
CHI2_2DOF_1PCT = 9.21
CHI2_1DOF_1PCT = 6.63


@dataclass(frozen=True)
class ModelSelection:
    """The selected intrinsics models.

    Attributes:
        bundle: the adjustment with the selected model (re-run when something changed and
            a re-run was asked for; else the given one).
        models: ``{camera: model description}`` (see :func:`describe_model`).
        start: (C, 15) camera parameters to re-run from (the given result's when nothing
            changed).
        free: (C, 15) bool, the free camera parameters of the selected model.
        square: (C,) bool, cameras whose fy is tied to fx in the selected model.
    """

    bundle: BundleResult
    models: dict[str, dict[str, str]]
    start: np.ndarray
    free: np.ndarray
    square: np.ndarray


def describe_model(free_row: np.ndarray, square: bool, fixed: bool) -> dict[str, str]:
    """Describe a camera's intrinsics model for the calibration file's metadata.

    Args:
        free_row: (15,) bool, the camera's free parameters.
        square: fy is tied to fx.
        fixed: the intrinsics were given (``--fix-intrinsics``).

    Returns:
        ``{"principal_point": ..., "distortion": ..., "focal": ...}``.
    """
    if fixed:
        return {"principal_point": "given", "distortion": "given", "focal": "given"}
    names = [n for n, f in zip(("k1", "k2", "p1", "p2", "k3"), free_row[DIST]) if f]
    return {
        "principal_point": "estimated" if free_row[2] else "image centre",
        "distortion": " ".join(names) if names else "none",
        "focal": "fx = fy" if square else "fx, fy",
    }


def _wald(value: np.ndarray, cov: np.ndarray) -> float:
    """Chi-square of ``value`` against zero under covariance ``cov`` (inf if singular)."""
    try:
        return float(value @ np.linalg.solve(cov, value))
    except np.linalg.LinAlgError:
        return float("inf")


def _simplify_camera(
    i: int,
    d: CameraDetections,
    cov: np.ndarray,
    cam: np.ndarray,
    free: np.ndarray,
    square: np.ndarray,
    opt: CalibrationOptions,
) -> bool:
    """Fix camera ``i``'s insignificant parameters in ``cam``, ``free`` and ``square``.

    Args:
        i: the camera's index.
        d: the camera's detections (for its name and image size).
        cov: (C, 15, 15) the cameras' parameter covariances.
        cam: (C, 15) camera parameters (updated in place).
        free: (C, 15) bool, the free parameters (updated in place).
        square: (C,) bool, cameras with fy tied to fx (updated in place).
        opt: the options (which parameters are tested).

    Returns:
        whether anything was fixed.
    """
    changed = False
    p = cam[i]
    if opt.principal_point == "auto" and free[i, 2]:
        centre = np.array([(d.size[0] - 1) / 2, (d.size[1] - 1) / 2])
        chi2 = _wald(p[PRINCIPAL] - centre, cov[i, PRINCIPAL, PRINCIPAL])
        logger.debug("camera %s: principal-point offset chi2 %.1f", d.name, chi2)
        if chi2 < CHI2_2DOF_1PCT:
            cam[i, PRINCIPAL] = centre
            free[i, PRINCIPAL] = False
            changed = True
    if opt.dist_model == "auto" and free[i, 6]:
        chi2 = _wald(p[TANGENTIAL], cov[i, TANGENTIAL, TANGENTIAL])
        logger.debug("camera %s: tangential distortion chi2 %.1f", d.name, chi2)
        if chi2 < CHI2_2DOF_1PCT:
            cam[i, TANGENTIAL] = 0.0
            free[i, TANGENTIAL] = False
            changed = True
    if opt.aspect == "auto" and free[i, 0] and free[i, 1]:
        # var(fx - fy) = var fx + var fy - 2 cov(fx, fy)
        c = cov[i, FOCAL, FOCAL]
        chi2 = _wald(np.array([p[0] - p[1]]), (c[0, 0] + c[1, 1] - 2 * c[0, 1])[None, None])
        logger.debug("camera %s: fx - fy = %.3f px, chi2 %.1f", d.name, p[0] - p[1], chi2)
        if chi2 < CHI2_1DOF_1PCT:
            cam[i, FOCAL] = 0.5 * (p[0] + p[1])
            free[i, 1] = False
            square[i] = True
            changed = True
    return changed


def select_models(
    ba: BundleResult,
    free: np.ndarray,
    square: np.ndarray,
    dets: Sequence[CameraDetections],
    fixed_names: frozenset[str],
    opt: CalibrationOptions,
    obs: Observations,
    rerun: bool = True,
) -> ModelSelection:
    """Drop principal-point offsets, tangential distortion and fx != fy the data do not support.

    With ``principal_point="auto"`` / ``dist_model="auto"`` / ``aspect="auto"``, a camera's
    principal-point offset from the image centre (cx, cy), its tangential terms (p1, p2) and
    the difference fx - fy are tested against zero with Wald chi-square tests on the bundle
    adjustment's covariance; what is not significant at 1 % is fixed (centre, zero, fy = fx)
    and, with ``rerun``, the bundle adjustment is re-run from the solution with the same
    inliers. Fewer free parameters make the remaining ones (rotations above all: a principal
    point error of 1 px tilts a camera by 1/f rad) less noisy.

    Args:
        ba: the bundle adjustment whose covariance is tested.
        free: (C, 15) bool, the adjustment's free parameters (not changed).
        square: (C,) bool, cameras with fy tied to fx (not changed).
        dets: per camera, the detections (names and image sizes).
        fixed_names: cameras whose intrinsics are given (never tested).
        opt: the options.
        obs: the observations ``ba`` was run on.
        rerun: re-run the adjustment when the model changed.

    Returns:
        the result, the model descriptions, and the parameters to re-run from.
    """
    cam = ba.cam_params
    free = free.copy()
    square = square.copy()
    changed = False
    if opt.principal_point == "auto" or opt.dist_model == "auto" or opt.aspect == "auto":
        cov = camera_covariance(ba, free, square)
        cam = ba.cam_params.copy()
        for i, d in enumerate(dets):
            if d.name not in fixed_names:
                changed |= _simplify_camera(i, d, cov, cam, free, square, opt)
        if changed and rerun:
            ba = run_bundle(cam, free, ba.frame_params, ba.frames, obs, opt, ba.f_scale, square, ba)
    models = {
        d.name: describe_model(free[i], bool(square[i]), d.name in fixed_names)
        for i, d in enumerate(dets)
    }
    return ModelSelection(ba, models, cam, free, square)
