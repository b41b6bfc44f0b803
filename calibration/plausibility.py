"""Physical plausibility of a calibration, checked after the bundle adjustment.

A calibration is refused (:class:`ImplausibleCalibrationError`) when a camera's field of
view lies outside :data:`FOV_RANGE_DEG`, its principal point lies more than
:data:`PRINCIPAL_MARGIN` of the image size outside the image, its radial distortion folds
where the board was (or anywhere in the image when the board reached its corners; a fold
only beyond the board's reach is a warning, :func:`folding_warnings`), the board poses
its own detections imply disagree with the rig's, the rig explains its detections much worse
than a calibration of the camera on its own (:data:`MAX_RIG_ERROR_RATIO`: its views do not
belong with the other cameras', e.g. mirrored, out of sync or from another recording), its
given intrinsics explain its
detections much worse than intrinsics fitted to the recording
(:mod:`freipose.calibration.given_intrinsics`), its focal length's standard error exceeds
:data:`MAX_FOCAL_SE` of the focal length, or the bundle adjustment rejected more than
:data:`MAX_OUTLIER_SHARE` of its detections. Its outlier threshold follows every camera's
own noise level (:func:`~freipose.calibration.robust.camera_noise_sigmas`), so a camera
whose corners are honestly noisier than the others' (strong distortion, blur, a board seen
through its back) keeps them, and what it rejects are gross errors (wrong ids, mirrored or
unsynchronized views).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from freipose.calibration.bundle import BundleResult
from freipose.calibration.intrinsics import CalibrationError
from freipose.calibration.params import CAM_PARAMS, DIST, FRAME_RVEC, FRAME_TVEC, RVEC, TVEC
from freipose.geometry.transforms import invert_transform, rodrigues, transform

__all__ = [
    "FOLD_MARGIN",
    "FOV_RANGE_DEG",
    "GOOD_COVERAGE",
    "MAX_FOCAL_SE",
    "MAX_OUTLIER_SHARE",
    "MAX_POSE_ANGLE_DEG",
    "MAX_POSE_SHIFT",
    "MAX_RIG_ERROR_RATIO",
    "PRINCIPAL_MARGIN",
    "Finding",
    "ImplausibleCalibrationError",
    "check_plausibility",
    "fold_pixel_radius",
    "folding_warnings",
]

FOV_RANGE_DEG = (5.0, 170.0)  # plausible horizontal field of view
PRINCIPAL_MARGIN = 0.25  # how far (share of the image size) the principal point may lie outside
MAX_OUTLIER_SHARE = 0.30  # share of a camera's detections the bundle adjustment may reject
MAX_POSE_ANGLE_DEG = 5.0  # median board-pose rotation disagreement of a camera
MAX_POSE_SHIFT = 0.10  # median board-centre disagreement, as a share of the board diagonal
MAX_FOCAL_SE = 0.05  # standard error of fx as a share of fx
# the rig's RMS error on a camera's kept detections may be this many times the RMS of the
# camera's calibration on its own, plus RIG_ERROR_ALLOWANCE_PX
MAX_RIG_ERROR_RATIO = 2.0
RIG_ERROR_ALLOWANCE_PX = 0.25
# a fold of the radial distortion is refused within this factor of the board's farthest
# corner (normalized radius), and anywhere in the image when the board reached this share
# of the image corner's radius; elsewhere it is a warning
FOLD_MARGIN = 1.1
GOOD_COVERAGE = 0.8
_POSE_FRAMES = 30  # frames per camera used for the board-pose comparison (evenly spaced)
_MIN_PNP_POINTS = 6

_FIX = (
    "pass --fix-intrinsics FILE (or --intrinsics-from) with intrinsics of this camera from "
    "a separate recording, leave the camera out, or record more frames with the board tilted "
    "and moved over the whole image"
)

_FIX_GIVEN = (
    "its intrinsics were given (--fix-intrinsics or --intrinsics-from): check that they "
    "belong to this camera (same lens, focus and resolution), or calibrate them anew"
)


@dataclass(frozen=True)
class Finding:
    """One reason a calibration is not plausible.

    Attributes:
        camera: the camera's name.
        check: ``field_of_view``, ``principal_point``, ``folding_distortion``,
            ``board_poses``, ``outliers``, ``rig_misfit``, ``given_intrinsics`` or
            ``weak_intrinsics``.
        message: the camera, the evidence (numbers) and the fix.
    """

    camera: str
    check: str
    message: str

    def to_dict(self) -> dict[str, str]:
        """The finding as ``summary.json`` holds it."""
        return {"camera": self.camera, "check": self.check, "message": self.message}


class ImplausibleCalibrationError(CalibrationError):
    """The calibration is not physically plausible; ``findings`` says why."""

    def __init__(self, findings: Sequence[Finding]) -> None:
        """Build the message from ``findings`` (one line each)."""
        self.findings = tuple(findings)
        lines = "\n".join(f"  - {f.message}" for f in self.findings)
        super().__init__(
            f"the calibration is not physically plausible, so it was not written:\n{lines}\n"
            f"Fix the recording as suggested, or pass --force to write it anyway (marked as "
            f"suspect in the file's metadata and the report)"
        )


def _fov_findings(name: str, size: tuple[int, int], p: np.ndarray, fix: str) -> list[Finding]:
    """Field of view and principal point of camera row ``p`` on a ``size`` image."""
    w, h = size
    out = []
    lo, hi = FOV_RANGE_DEG
    fx, fy = float(p[0]), float(p[1])
    fov = [2 * np.degrees(np.arctan2(s / 2, f)) if f > 0 else 180.0 for s, f in ((w, fx), (h, fy))]
    if not (lo <= fov[0] <= hi) or fy <= 0 or fov[1] > hi:
        out.append(
            Finding(
                name,
                "field_of_view",
                f"camera {name}: focal length fx = {fx:.1f}, fy = {fy:.1f} px on a {w}x{h} "
                f"image gives a horizontal field of view of {fov[0]:.1f} degrees (plausible: "
                f"{lo:.0f}-{hi:.0f}); {fix}",
            )
        )
    cx, cy = float(p[2]), float(p[3])
    m = PRINCIPAL_MARGIN
    if not (-m * w <= cx <= (1 + m) * w and -m * h <= cy <= (1 + m) * h):
        out.append(
            Finding(
                name,
                "principal_point",
                f"camera {name}: principal point ({cx:.1f}, {cy:.1f}) px lies more than "
                f"{100 * m:.0f} % of the image size outside the {w}x{h} image; {fix}",
            )
        )
    return out


def folding_radius(dist: np.ndarray, corner_radius: float) -> float | None:
    """Where the radial distortion folds before reaching the image corner, else ``None``.

    The radial map ``r_d = r (1 + k1 r² + k2 r⁴ + k3 r⁶)`` of normalized radii must rise
    until it reaches ``corner_radius`` (the image corner's normalized distorted radius);
    otherwise image points near the corner belong to two rays, or to none.

    Args:
        dist: (5,) k1 k2 p1 p2 k3.
        corner_radius: the image corner's normalized radius.

    Returns:
        the undistorted radius where the map stops rising, or ``None`` when it reaches the
        corner first (or never stops rising within 4 times the corner's radius).
    """
    k1, k2, k3 = float(dist[0]), float(dist[1]), float(dist[4])
    r = np.linspace(0.0, 4.0 * corner_radius, 4001)
    r2 = r * r
    slope = 1 + 3 * k1 * r2 + 5 * k2 * r2**2 + 7 * k3 * r2**3
    rd = r * (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3)
    stop = np.flatnonzero(slope <= 0)
    reach = np.flatnonzero(rd >= corner_radius)
    if stop.size and (not reach.size or stop[0] < reach[0]):
        return float(r[stop[0]])
    return None


def _covered_radius(ba: BundleResult, camera: int) -> float:
    """The largest normalized distorted radius of a camera's inlier detections (0: none)."""
    p = ba.cam_params[camera]
    mine = ba.inliers & (ba.obs.cam == camera)
    if not mine.any() or not (p[0] > 0 and p[1] > 0):
        return 0.0
    uv = ba.obs.uv[mine]
    return float(np.hypot((uv[:, 0] - p[2]) / p[0], (uv[:, 1] - p[3]) / p[1]).max())


@dataclass(frozen=True)
class _Fold:
    """Where a camera's radial distortion folds, and what the board covered.

    Attributes:
        reach: the largest distorted radius the model reaches (normalized).
        at: the undistorted radius where it stops rising (normalized).
        covered: the largest distorted radius of the camera's detections (normalized).
        corner: the image corner's distorted radius (normalized).
        px: pixels per normalized unit (the mean focal length).
        coefficients: ``k1 = ..., k2 = ..., k3 = ...`` for the messages.
    """

    reach: float
    at: float
    covered: float
    corner: float
    px: float
    coefficients: str

    @property
    def refused(self) -> bool:
        """The fold lies where the board was, or inside an image the board covered well."""
        if self.reach < FOLD_MARGIN * self.covered:
            return True
        return self.covered >= GOOD_COVERAGE * self.corner


def _fold(size: tuple[int, int], p: np.ndarray, covered: float) -> _Fold | None:
    """Where camera row ``p``'s radial distortion folds inside a ``size`` image, else None."""
    w, h = size
    if not (p[0] > 0 and p[1] > 0):
        return None
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], float)
    rc = float(np.hypot((corners[:, 0] - p[2]) / p[0], (corners[:, 1] - p[3]) / p[1]).max())
    r = folding_radius(p[DIST], rc)
    if r is None:
        return None
    k1, k2, k3 = (float(x) for x in p[DIST][[0, 1, 4]])
    reach = r * (1 + k1 * r**2 + k2 * r**4 + k3 * r**6)
    k = f"k1 = {k1:.4g}, k2 = {k2:.4g}, k3 = {k3:.4g}"
    return _Fold(reach, r, covered, rc, 0.5 * float(p[0] + p[1]), k)


def fold_pixel_radius(K: np.ndarray, dist: np.ndarray, size: tuple[int, int]) -> float | None:
    """How far (px) from the principal point the radial distortion folds inside the image.

    Args:
        K: (3, 3) intrinsic matrix.
        dist: (5,) k1 k2 p1 p2 k3.
        size: the image size (width, height).

    Returns:
        the largest distorted radius (px, at the mean focal length) the model reaches, or
        ``None`` when it reaches the image corners.
    """
    p = np.zeros(CAM_PARAMS)
    p[:4] = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    p[DIST] = dist
    fold = _fold(size, p, 0.0)
    return None if fold is None else fold.reach * fold.px


def _folding_findings(name: str, fold: _Fold | None, fix: str) -> list[Finding]:
    """A finding when a camera's radial distortion folds where it must not (see _Fold)."""
    if fold is None or not fold.refused:
        return []
    f = fold
    return [
        Finding(
            name,
            "folding_distortion",
            f"camera {name}: the radial distortion ({f.coefficients}) folds the image: the "
            f"distorted radius rises only to {f.reach:.3f} (normalized, {f.reach * f.px:.0f} px "
            f"from the principal point; at undistorted radius {f.at:.3f}) and falls after "
            f"that, short of the image corner at {f.corner:.3f}, while the board's corners "
            f"reached {f.covered:.3f} ({f.covered * f.px:.0f} px); {fix}, or choose a simpler "
            f"--dist-model",
        )
    ]


def _folding_warning(name: str, fold: _Fold | None) -> list[str]:
    """A warning when a camera's distortion folds outside the board's reach only."""
    if fold is None or fold.refused:
        return []
    f = fold
    return [
        f"camera {name}: the lens model ({f.coefficients}) fits the board's views, which "
        f"reached {f.covered * f.px:.0f} px from the principal point (normalized radius "
        f"{f.covered:.3f}), but folds {f.reach * f.px:.0f} px out ({f.reach:.3f}), short of the "
        f"image corner ({f.corner * f.px:.0f} px, {f.corner:.3f}): image points farther out "
        f"cannot be undistorted and 3D points seen there are projected wrongly; record board "
        f"views nearer the image corners (the report's coverage_{name}.png shows where the "
        f"board was)"
    ]


def folding_warnings(
    names: Sequence[str], sizes: Sequence[tuple[int, int]], ba: BundleResult
) -> list[str]:
    """Warnings for cameras whose distortion folds beyond the board's reach, inside the image.

    Such a model fits the detections and is kept (:func:`check_plausibility` refuses only a
    fold inside the board's reach, or inside an image the board covered out to
    :data:`GOOD_COVERAGE` of the corner radius); the warning names the region it fails in.

    Args:
        names: the camera names, in rig order.
        sizes: their image sizes (width, height).
        ba: the final bundle adjustment.

    Returns:
        one message per such camera.
    """
    out: list[str] = []
    for i, (name, size) in enumerate(zip(names, sizes)):
        out += _folding_warning(name, _fold(size, ba.cam_params[i], _covered_radius(ba, i)))
    return out


def _pose_disagreement(ba: BundleResult, camera: int, diag: float) -> tuple[float, float, int]:
    """Median rotation (deg) and board-centre shift (share of ``diag``) of one camera.

    For the board poses seen by this camera and at least one other, the pose that the
    camera's own inlier detections imply (PnP with its adjusted intrinsics, from the rig's
    pose) is compared with the rig's pose.

    Returns:
        the medians and the number of poses compared (0: none, medians NaN).
    """
    obs, keep = ba.obs, ba.inliers
    p = ba.cam_params[camera]
    K = np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1.0]])
    dist = p[DIST].astype(np.float64)
    Tc = transform(rodrigues(p[RVEC]), p[TVEC])
    F = len(ba.frames)
    seen = np.zeros((F, len(ba.cam_params)), bool)
    seen[obs.frame[keep], obs.cam[keep]] = True
    idx = np.flatnonzero(keep & (obs.cam == camera))
    idx = idx[np.argsort(obs.frame[idx], kind="stable")]
    ks, starts, cnt = np.unique(obs.frame[idx], return_index=True, return_counts=True)
    use = (cnt >= _MIN_PNP_POINTS) & (seen[ks].sum(1) >= 2)
    ks, starts, cnt = ks[use], starts[use], cnt[use]
    if ks.size > _POSE_FRAMES:
        pick = np.linspace(0, ks.size - 1, _POSE_FRAMES).round().astype(int)
        ks, starts, cnt = ks[pick], starts[pick], cnt[pick]
    angles, shifts = [], []
    pts = obs.point[idx]
    centre = np.append(0.5 * (pts.min(0)[:2] + pts.max(0)[:2]), 0.0) if idx.size else np.zeros(3)
    Tc_inv = invert_transform(Tc)
    for k, s0, n in zip(ks, starts, cnt):
        m = idx[s0 : s0 + n]
        fr = ba.frame_params[k].astype(np.float64)
        B = transform(cv2.Rodrigues(fr[FRAME_RVEC])[0], fr[FRAME_TVEC])
        T0 = Tc @ B
        rv, tv = cv2.Rodrigues(T0[:3, :3])[0], T0[:3, 3].reshape(3, 1).copy()
        ok, rv, tv = cv2.solvePnP(
            obs.point[m].astype(np.float64),
            obs.uv[m].astype(np.float64),
            K,
            dist,
            rv,
            tv,
            useExtrinsicGuess=True,
            flags=cv2.SOLVEPNP_ITERATIVE,
        )
        if not ok:
            continue
        Bc = Tc_inv @ transform(cv2.Rodrigues(rv)[0], tv.ravel())
        dR = B[:3, :3].T @ Bc[:3, :3]
        angles.append(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1.0, 1.0))))
        shift = (Bc[:3, :3] - B[:3, :3]) @ centre + Bc[:3, 3] - B[:3, 3]
        shifts.append(np.linalg.norm(shift))
    if not angles:
        return float("nan"), float("nan"), 0
    return float(np.median(angles)), float(np.median(shifts)) / diag, len(angles)


def _pose_findings(
    ba: BundleResult, camera: int, name: str, diag: float, fix: str
) -> list[Finding]:
    """A finding when camera ``camera``'s board poses disagree with the rig's."""
    angle, shift, n = _pose_disagreement(ba, camera, diag)
    if n == 0 or (angle <= MAX_POSE_ANGLE_DEG and shift <= MAX_POSE_SHIFT):
        return []
    return [
        Finding(
            name,
            "board_poses",
            f"camera {name}: the board poses its own detections imply disagree with the other "
            f"cameras' in {n} shared frames: median {angle:.1f} degrees and {100 * shift:.0f} % "
            f"of the board diagonal (plausible: at most {MAX_POSE_ANGLE_DEG:.0f} degrees and "
            f"{100 * MAX_POSE_SHIFT:.0f} %); check that its video belongs to this recording "
            f"and is synchronized and not mirrored, or leave the camera out; {fix}",
        )
    ]


def _outlier_findings(ba: BundleResult, camera: int, name: str, fix: str) -> list[Finding]:
    """A finding when most of a camera's detections lie far beyond its own noise level."""
    mine = ba.obs.cam == camera
    n = int(mine.sum())
    bad = int((mine & ~ba.inliers).sum())
    if n == 0 or bad / n <= MAX_OUTLIER_SHARE:
        return []
    return [
        Finding(
            name,
            "outliers",
            f"camera {name}: the bundle adjustment rejected {bad} of its {n} detections "
            f"({100 * bad / n:.0f} %, plausible: at most {100 * MAX_OUTLIER_SHARE:.0f} %) as "
            f"further from their projection than the camera's own noise allows; its views do "
            f"not fit one camera model (is its video mirrored, from another recording or out "
            f"of sync?); {fix}",
        )
    ]


def _misfit_findings(
    ba: BundleResult, camera: int, name: str, own_rms: float | None, fix: str
) -> list[Finding]:
    """A finding when the rig explains a camera's detections much worse than it alone does."""
    mine = ba.inliers & (ba.obs.cam == camera)
    if own_rms is None or not np.isfinite(own_rms) or not mine.any():
        return []
    rig_rms = float(np.sqrt(np.mean(ba.errors[mine] ** 2)))
    if rig_rms <= MAX_RIG_ERROR_RATIO * own_rms + RIG_ERROR_ALLOWANCE_PX:
        return []
    return [
        Finding(
            name,
            "rig_misfit",
            f"camera {name}: its detections fit a camera of their own at {own_rms:.2f} px RMS, "
            f"but the rig (board poses shared with the other cameras) explains them only at "
            f"{rig_rms:.2f} px (plausible: at most {MAX_RIG_ERROR_RATIO:.0f} times that plus "
            f"{RIG_ERROR_ALLOWANCE_PX} px); its views do not fit the other cameras' (is its "
            f"video mirrored, from another recording or out of sync?); {fix}",
        )
    ]


def _given_findings(name: str, errors: tuple[float, float] | None) -> list[Finding]:
    """A finding when the given intrinsics explain the camera's detections much worse."""
    if errors is None:
        return []
    given, fitted = errors
    return [
        Finding(
            name,
            "given_intrinsics",
            f"camera {name}: its given intrinsics explain its detections at a median error of "
            f"{given:.2f} px, intrinsics fitted to this recording at {fitted:.2f} px; "
            f"{_FIX_GIVEN}",
        )
    ]


def _weak_findings(name: str, p: np.ndarray, se: Mapping[str, float], fix: str) -> list[Finding]:
    """A finding when camera row ``p``'s focal length is poorly determined."""
    s = se.get("fx")
    if s is None or not p[0] > 0 or s <= MAX_FOCAL_SE * p[0]:
        return []
    return [
        Finding(
            name,
            "weak_intrinsics",
            f"camera {name}: its focal length fx = {p[0]:.1f} px has a standard error of "
            f"{s:.1f} px ({100 * s / p[0]:.0f} %, plausible: at most "
            f"{100 * MAX_FOCAL_SE:.0f} %); {fix}",
        )
    ]


def check_plausibility(
    names: Sequence[str],
    sizes: Sequence[tuple[int, int]],
    ba: BundleResult,
    board_diagonal: float,
    standard_errors: Mapping[str, Mapping[str, float]],
    fixed: frozenset[str] = frozenset(),
    given_errors: Mapping[str, tuple[float, float]] | None = None,
    own_rms: Mapping[str, float] | None = None,
) -> tuple[Finding, ...]:
    """Every reason the adjusted rig is not physically plausible (see the module docstring).

    Args:
        names: the camera names, in rig order.
        sizes: their image sizes (width, height).
        ba: the final bundle adjustment.
        board_diagonal: the board's diagonal (mm), the scale of the board-pose comparison.
        standard_errors: per camera, the standard errors of its free intrinsics
            (:func:`freipose.calibration.stats.intrinsic_standard_errors`).
        fixed: the cameras whose intrinsics were given (their findings point at the file).
        given_errors: per given-intrinsics camera that a free fit explains much better, the
            median errors (px) with the given and the fitted intrinsics
            (:func:`~freipose.calibration.given_intrinsics.given_intrinsics_errors`).
        own_rms: per camera, the RMS error (px) of its calibration on its own (cameras
            without one are not compared with it).

    Returns:
        the findings, in camera order (empty: plausible).
    """
    out: list[Finding] = []
    for i, (name, size) in enumerate(zip(names, sizes)):
        p = ba.cam_params[i]
        fix = _FIX_GIVEN if name in fixed else _FIX
        out += _fov_findings(name, size, p, fix)
        out += _folding_findings(name, _fold(size, p, _covered_radius(ba, i)), fix)
        out += _outlier_findings(ba, i, name, fix)
        out += _given_findings(name, (given_errors or {}).get(name))
        if len(names) > 1:
            out += _misfit_findings(ba, i, name, (own_rms or {}).get(name), fix)
        out += _weak_findings(name, p, standard_errors.get(name, {}), fix)
        if len(names) > 1:
            out += _pose_findings(ba, i, name, board_diagonal, fix)
    return tuple(out)


def findings_metadata(findings: Sequence[Finding]) -> list[dict[str, Any]]:
    """The findings as the calibration file's ``metadata.suspect`` holds them."""
    return [f.to_dict() for f in findings]
