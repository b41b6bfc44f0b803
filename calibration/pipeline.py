"""The calibration pipeline: detections -> intrinsics -> extrinsics -> bundle adjustment -> world.

``calibrate(sources, board, output, options)`` runs everything from videos (detections are
cached next to the output); ``calibrate_detections(detections, board, options)`` starts from
detections (tests, other detectors).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import numpy as np

from freipose.calibration.boards import Board
from freipose.calibration.bundle import (
    BundleResult,
    Observations,
    board_point_offsets,
    bundle_adjust,
    camera_covariance,
    matrix_to_rvec,
    rodrigues,
)
from freipose.calibration.detect import CameraDetections, detect_cameras, diagnose_board
from freipose.calibration.extrinsics import (
    CameraGraph,
    board_poses_per_camera,
    initial_board_poses,
    initial_extrinsics,
)
from freipose.calibration.intrinsics import (
    CalibrationError,
    IntrinsicsResult,
    calibrate_intrinsics,
    dist_free_mask,
)
from freipose.geometry import Camera, CameraRig

_In = TypeVar("_In")
_Out = TypeVar("_Out")

logger = logging.getLogger(__name__)

__all__ = [
    "CalibrationError",
    "CalibrationOptions",
    "CalibrationResult",
    "CameraStats",
    "calibrate",
    "calibrate_detections",
    "detection_cache_dir",
]

HIGH_ERROR_PX = 1.0
# model selection: a camera keeps a principal-point offset or tangential distortion only when
# the bundle adjustment's estimate differs from zero by more than this Wald chi-square
# (2 degrees of freedom, 1 % significance)
# (the fx = fy test has 1 degree of freedom)
CHI2_2DOF_1PCT = 9.21
CHI2_1DOF_1PCT = 6.63
PRINCIPAL_POINT_MODES = ("auto", "free", "centre")
ASPECT_MODES = ("auto", "free", "square")
# board frame (x right, y down the print, z into the board) -> floor frame (z up out of it)
BOARD_TO_FLOOR = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class CalibrationOptions:
    """Solver options.

    Attributes:
        origin_frame: video frame whose board pose defines the world (board on the floor: origin
            at the board's top-left pattern corner, x along the board's rows, z up out of the
            floor); ``None`` = the first camera's frame.
        intrinsics_only: stop after per-camera intrinsics (extrinsics are identity).
        fixed_intrinsics: a rig whose K and distortion are used (and kept fixed) for every
            camera of the same name.
        dist_model: ``auto`` (default: k1 k2, plus p1 p2 for a camera where the tangential
            terms are significant), ``none``, ``k1``, ``k1k2``, ``k1k2p`` (k1 k2 p1 p2) or
            ``full`` (k1 k2 p1 p2 k3).
        principal_point: ``auto`` (default: the image centre unless the bundle adjustment
            finds a significant offset), ``free`` or ``centre`` (fixed at
            ``((w - 1) / 2, (h - 1) / 2)``).
        aspect: ``auto`` (default: fy = fx, square pixels, unless the bundle adjustment finds
            them significantly different), ``free`` (fx and fy estimated separately) or
            ``square`` (always fy = fx).
        jobs: detection processes, and threads that initialise the cameras (default: CPU
            count).
        max_views: views per camera for the intrinsics initialisation.
        loss, f_scale: robust loss of the bundle adjustment and its scale (px); ``None``
            estimates the scale from the detection noise (see
            :func:`freipose.calibration.bundle.bundle_adjust`).
        outlier_px: minimum rejection threshold (px); detections further than
            ``max(outlier_px, 5 σ)`` from their projection are rejected.
        solver: ``lm`` (Schur-complement Levenberg-Marquardt) or ``scipy`` (least_squares).
        refine_board: after the bundle adjustment, correct every board point's position in
            the board plane (printing errors, and each corner's own detection bias, which is
            the same in every view) and adjust again; once before and once after the model
            selection (see :func:`freipose.calibration.bundle.board_point_offsets`; the board
            keeps its printed size).
        view_weights: weight every board view's detections by that view's own noise level
            (σ / σ_view, estimated from its residuals after the first round; see
            :func:`freipose.calibration.bundle.view_noise_scales`): blurred or steep views
            count less.
    """

    origin_frame: int | None = None
    intrinsics_only: bool = False
    fixed_intrinsics: CameraRig | None = None
    dist_model: str = "auto"
    principal_point: str = "auto"
    aspect: str = "auto"
    jobs: int | None = None
    max_views: int = 40
    loss: str = "huber"
    f_scale: float | None = None
    outlier_px: float = 0.5
    solver: str = "lm"
    progress: bool = True
    refine_board: bool = True
    view_weights: bool = True


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

    def to_dict(self) -> dict:
        return {
            "frames_with_detections": self.frames_detected,
            "points_detected": self.points_detected,
            "points_used": self.points_used,
            "reprojection_rms_px": round(self.rms, 4) if np.isfinite(self.rms) else None,
            "reprojection_median_px": round(self.median, 4) if np.isfinite(self.median) else None,
            "intrinsics_frames": self.intrinsics_frames,
        }


@dataclass(frozen=True)
class CalibrationResult:
    """Everything a report needs.

    Attributes:
        rig: the calibrated cameras (world→camera, mm).
        board: the board.
        detections: per camera (F frames each, common prefix).
        stats: per camera, in rig order.
        board_poses: (F, 4, 4) board→world per frame, NaN where not estimated.
        world: the world-frame definition (also in ``rig.metadata["world"]``).
        graph: camera graph (None for ``intrinsics_only``).
        bundle: bundle-adjustment result (None for ``intrinsics_only``).
        warnings: messages for the user.
        intrinsics: per-camera initial intrinsics.
        board_offsets: (P, 2) mm in-plane corrections of the board points (``refine_board``).
    """

    rig: CameraRig
    board: Board
    detections: list[CameraDetections]
    stats: list[CameraStats]
    board_poses: np.ndarray
    world: str
    graph: CameraGraph | None = None
    bundle: BundleResult | None = None
    warnings: list[str] = field(default_factory=list)
    intrinsics: dict[str, IntrinsicsResult] = field(default_factory=dict)
    board_offsets: np.ndarray | None = None

    def camera_errors(self, camera: int) -> np.ndarray:
        """Final reprojection errors (px) of the inlier detections of camera index ``camera``."""
        if self.bundle is None:
            return np.zeros(0)
        b = self.bundle
        m = (b.obs.cam == camera) & b.inliers
        return b.errors[m]


def _T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _inv(T: np.ndarray) -> np.ndarray:
    return _T(T[:3, :3].T, -T[:3, :3].T @ T[:3, 3])


def _common_prefix(detections: list[CameraDetections], warnings: list[str]):
    counts = [d.num_frames for d in detections]
    n = min(counts)
    if len(set(counts)) > 1:
        desc = ", ".join(f"{d.name}: {d.num_frames}" for d in detections)
        msg = (
            f"the cameras have different frame counts ({desc}); using the first {n} frames of "
            f"each. If the videos are not synchronized from frame 0, trim them first"
        )
        logger.warning(msg)
        warnings.append(msg)
        detections = [d.truncated(n) for d in detections]
    return detections


def _check_detected(detections: list[CameraDetections], board: Board) -> None:
    empty = [d.name for d in detections if not d.mask.any()]
    if empty:
        raise CalibrationError(
            f"the board was never detected in camera(s) {', '.join(empty)}; check that the board "
            f"file matches the printed board ({board.to_dict()}) and that those cameras see it"
        )


def calibrate_detections(
    detections: Sequence[CameraDetections],
    board: Board,
    options: CalibrationOptions | None = None,
) -> CalibrationResult:
    """Calibrate a rig from per-camera detections of ``board`` (synchronized by frame index).

    The same detections give the same calibration to the last bit: the solver's OpenCV calls
    run on one OpenCV thread (OpenCV's multi-threaded ``calibrateCamera`` sums in a varying
    order, which moved the results by up to ~1e-8 px or mm between runs; the setting is
    process-wide and given back afterwards), and the cameras' intrinsics and board poses are
    initialised in up to ``options.jobs`` threads instead.
    """
    from freipose.io.video import opencv_threads

    with opencv_threads(1):
        return _calibrate_detections(detections, board, options or CalibrationOptions())


def _map_cameras(fn: Callable[[_In], _Out], items: Sequence[_In], jobs: int | None) -> list[_Out]:
    """``[fn(x) for x in items]`` in up to ``jobs`` threads (default: CPU count); OpenCV
    releases the interpreter while it computes."""
    n = min(len(items), jobs or os.cpu_count() or 1)
    if n <= 1:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(n) as ex:
        return list(ex.map(fn, items))


def _calibrate_detections(
    detections: Sequence[CameraDetections], board: Board, opt: CalibrationOptions
) -> CalibrationResult:
    warnings: list[str] = []
    dets = _common_prefix(list(detections), warnings)
    if not dets:
        raise CalibrationError("no cameras given")
    names = [d.name for d in dets]
    if len(set(names)) != len(names):
        raise CalibrationError(
            f"camera names must be unique (they are the file or folder stems): {names}"
        )
    _check_detected(dets, board)
    obj = board.object_points
    F = dets[0].num_frames
    C = len(dets)
    free_dist = dist_free_mask(opt.dist_model)
    if opt.principal_point not in PRINCIPAL_POINT_MODES:
        raise CalibrationError(
            f"unknown principal_point mode {opt.principal_point!r}; expected one of "
            f"{', '.join(PRINCIPAL_POINT_MODES)}"
        )
    if opt.aspect not in ASPECT_MODES:
        raise CalibrationError(
            f"unknown aspect mode {opt.aspect!r}; expected one of {', '.join(ASPECT_MODES)}"
        )

    # ---- intrinsics
    Ks, dists = [], []
    fixed_names: set[str] = set()
    to_calibrate = []
    for d in dets:
        if opt.fixed_intrinsics is not None:
            if d.name not in opt.fixed_intrinsics:
                raise CalibrationError(
                    f"camera {d.name} is not in the --fix-intrinsics file (it has "
                    f"{', '.join(opt.fixed_intrinsics.names)}); name the videos like its cameras"
                )
            cam = opt.fixed_intrinsics[d.name]
            if tuple(cam.size) != tuple(d.size):
                raise CalibrationError(
                    f"camera {d.name}: the --fix-intrinsics file is for {cam.size[0]}x"
                    f"{cam.size[1]} images but the video is {d.size[0]}x{d.size[1]}"
                )
            fixed_names.add(d.name)
        else:
            to_calibrate.append(d)
    results = _map_cameras(
        lambda d: calibrate_intrinsics(
            d.points,
            obj,
            d.size,
            opt.dist_model,
            camera=d.name,
            max_views=opt.max_views,
            fix_principal_point=opt.principal_point == "centre",
        ),
        to_calibrate,
        opt.jobs,
    )
    intr = {d.name: res for d, res in zip(to_calibrate, results)}
    for d in dets:
        if d.name in fixed_names:
            cam = opt.fixed_intrinsics[d.name]
            Ks.append(cam.K.copy())
            dists.append(cam.dist.copy())
            continue
        res = intr[d.name]
        if res.max_tilt_difference_deg < 10.0 or res.coverage < 0.1:
            warnings.append(
                f"camera {d.name}: intrinsics rest on {len(res.frames)} board views covering "
                f"{100 * res.coverage:.0f} % of the image with tilts differing by at most "
                f"{res.max_tilt_difference_deg:.0f} degrees; record more frames with the board "
                f"tilted and moved over the whole image, or pass --fix-intrinsics"
            )
        Ks.append(res.K)
        dists.append(res.dist)
        logger.info(
            "camera %s: intrinsics from %d views, RMS %.3f px, f = %.1f, %.1f",
            d.name,
            len(res.frames),
            res.rms,
            res.K[0, 0],
            res.K[1, 1],
        )

    if opt.intrinsics_only:
        cams = tuple(
            Camera(d.name, tuple(d.size), Ks[i], dists[i], np.eye(3), np.zeros(3))
            for i, d in enumerate(dets)
        )
        world = "intrinsics only: extrinsics are identity (not calibrated)"
        rig = CameraRig(cams, {"world": world, "calibrated_by": "freipose calib"})
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
        _warn_high(stats, warnings)
        return CalibrationResult(
            rig, board, dets, stats, np.full((F, 4, 4), np.nan), world, None, None, warnings, intr
        )

    # ---- board poses, camera graph, initial extrinsics
    poses = np.stack(
        _map_cameras(
            lambda i: board_poses_per_camera(dets[i].points, obj, Ks[i], dists[i])[0],
            range(C),
            opt.jobs,
        )
    )  # (C, F, 4, 4)
    for i, d in enumerate(dets):
        if not np.isfinite(poses[i, :, 0, 0]).any():
            raise CalibrationError(
                f"camera {d.name}: no frame gives a consistent board pose (reprojection error "
                f"< 3 px with the estimated intrinsics); the detections or the board's "
                f"dimensions are wrong"
            )
    T_world, graph = initial_extrinsics(names, poses)
    counts = np.stack([d.counts for d in dets])
    B0 = initial_board_poses(T_world, poses, counts)
    frames = np.flatnonzero(np.isfinite(B0[:, 0, 0]))
    frame_pos = np.full(F, -1)
    frame_pos[frames] = np.arange(len(frames))

    # ---- observations: every detection in a frame with a board pose
    cam_i, fr_i, pt_i, uv = [], [], [], []
    for i, d in enumerate(dets):
        m = d.mask & (frame_pos >= 0)[:, None]
        f_idx, p_idx = np.nonzero(m)
        cam_i.append(np.full(len(f_idx), i))
        fr_i.append(frame_pos[f_idx])
        pt_i.append(p_idx)
        uv.append(d.points[f_idx, p_idx])
    obs = Observations(
        np.concatenate(cam_i),
        np.concatenate(fr_i),
        obj[np.concatenate(pt_i)],
        np.concatenate(uv),
    )

    cam0 = np.zeros((C, 15))
    free = np.zeros((C, 15), bool)
    square = np.zeros(C, bool)  # fy tied to fx
    for i, d in enumerate(dets):
        K = Ks[i]
        cam0[i, :4] = (K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        cam0[i, 4:9] = dists[i]
        cam0[i, 9:12] = matrix_to_rvec(T_world[i, :3, :3])
        cam0[i, 12:15] = T_world[i, :3, 3]
        if d.name not in fixed_names:
            free[i, :4] = True
            free[i, 4:9] = free_dist
            if opt.principal_point == "centre":
                cam0[i, 2:4] = ((d.size[0] - 1) / 2, (d.size[1] - 1) / 2)
                free[i, 2:4] = False
            if opt.aspect == "square":
                cam0[i, :2] = 0.5 * (K[0, 0] + K[1, 1])
                free[i, 1] = False
                square[i] = True
        if i != graph.root:
            free[i, 9:] = True
    fr0 = np.zeros((len(frames), 6))
    for k, f in enumerate(frames):
        fr0[k, :3] = matrix_to_rvec(B0[f, :3, :3])
        fr0[k, 3:] = B0[f, :3, 3]
    ba = _bundle(cam0, free, fr0, frames, obs, opt, square=square)
    offsets = np.zeros((len(obj), 2))
    point_ids = np.concatenate(pt_i)

    def refine(ba: BundleResult, start: np.ndarray, obs: Observations):
        nonlocal offsets
        offsets = offsets + board_point_offsets(ba, point_ids, len(obj))
        pts = obj.copy()
        pts[:, :2] += offsets
        obs = Observations(obs.cam, obs.frame, pts[point_ids], obs.uv)
        return _bundle(start, free, ba.frame_params, frames, obs, opt, ba.f_scale, square, ba), obs

    # with refine_board: correct the board once before the model selection (per-corner
    # detector biases otherwise pass for principal-point offsets or tangential distortion),
    # and once more with the selected model (that adjustment also serves the selection)
    if opt.refine_board:
        ba, obs = refine(ba, ba.cam_params, obs)
    ba, models, start = _select_models(
        ba, free, square, dets, fixed_names, opt, frames, obs, rerun=not opt.refine_board
    )
    offsets_rms = 0.0
    if opt.refine_board:
        ba, obs = refine(ba, start, obs)
        offsets_rms = float(np.sqrt(np.mean(np.sum(offsets**2, axis=1))))
        logger.info(
            "board points corrected by %.3f mm RMS (max %.3f mm)",
            offsets_rms,
            float(np.linalg.norm(offsets, axis=1).max()),
        )
    logger.info(
        "bundle adjustment: RMS %.3f -> %.3f px in %.2f s (%d evaluations)",
        ba.initial_rms,
        float(np.sqrt(np.mean(ba.errors[ba.inliers] ** 2))),
        ba.seconds,
        ba.nfev,
    )

    # ---- world frame
    Tc = np.stack([_T(rodrigues(p[9:12]), p[12:15]) for p in ba.cam_params])  # world→cam
    Bw = np.full((F, 4, 4), np.nan)
    for k, f in enumerate(frames):
        Bw[f] = _T(rodrigues(ba.frame_params[k, :3]), ba.frame_params[k, 3:])
    if opt.origin_frame is not None:
        N = int(opt.origin_frame)
        if not (0 <= N < F) or not np.isfinite(Bw[N, 0, 0]):
            seen = np.flatnonzero(np.isfinite(Bw[:, 0, 0]))
            near = seen[np.argsort(np.abs(seen - N))[:5]] if len(seen) else []
            raise CalibrationError(
                f"--origin-frame {N}: the board pose in that frame is unknown (no camera "
                f"detected enough of the board; the videos have {F} frames). Frames with a board "
                f"pose near it: {', '.join(str(int(x)) for x in sorted(near))}"
            )
        W = BOARD_TO_FLOOR @ _inv(Bw[N])
        world = (
            f"board on the floor in frame {N}: origin at the board's top-left pattern corner, "
            f"x along the board's rows, y toward its first row, z up out of the floor; mm"
        )
    else:
        W = Tc[0].copy()
        world = (
            f"camera {names[0]}'s frame (origin at its optical centre, x right, y down, "
            f"z forward); mm"
        )
    Tc = np.stack([T @ _inv(W) for T in Tc])
    Bw = np.einsum("ij,fjk->fik", W, Bw)

    cams = []
    for i, d in enumerate(dets):
        p = ba.cam_params[i]
        K = np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1.0]])
        R = Tc[i, :3, :3]
        U, _s, Vt = np.linalg.svd(R)
        cams.append(Camera(d.name, tuple(d.size), K, p[4:9].copy(), U @ Vt, Tc[i, :3, 3]))
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
    _warn_high(stats, warnings)
    rms_all = float(np.sqrt(np.mean(ba.errors[ba.inliers] ** 2)))
    metadata = {
        "world": world,
        "calibrated_by": "freipose calib",
        "board": board.to_dict(),
        "reprojection_rms_px": round(rms_all, 4),
        "distortion_model": opt.dist_model,
        "intrinsics_model": models,
        "view_weights": bool(opt.view_weights),
    }
    if opt.refine_board:
        metadata["board_point_corrections_rms_mm"] = round(offsets_rms, 4)
    if opt.origin_frame is not None:
        metadata["origin_frame"] = int(opt.origin_frame)
    rig = CameraRig(tuple(cams), metadata)
    return CalibrationResult(
        rig, board, dets, stats, Bw, world, graph, ba, warnings, intr,
        offsets if opt.refine_board else None,
    )  # fmt: skip


def _bundle(
    cam, free, fr, frames, obs, opt: CalibrationOptions, start_scale=1.0, square=None, prev=None
) -> BundleResult:
    """Bundle adjustment with the options; ``prev`` (a result on the same observations) gives
    the starting inliers and view weights."""
    return bundle_adjust(
        cam,
        free,
        fr,
        frames,
        obs,
        loss=opt.loss,
        f_scale=opt.f_scale,
        outlier_px=opt.outlier_px,
        method=opt.solver,
        start_f_scale=start_scale,
        equal_focal=square,
        keep=None if prev is None else prev.inliers,
        view_weighting=opt.view_weights,
        view_scale=None if prev is None else prev.view_scale,
    )


def _describe_model(free_row: np.ndarray, square: bool, fixed: bool) -> dict:
    if fixed:
        return {"principal_point": "given", "distortion": "given", "focal": "given"}
    names = [n for n, f in zip(("k1", "k2", "p1", "p2", "k3"), free_row[4:9]) if f]
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


def _select_models(
    ba: BundleResult,
    free: np.ndarray,
    square: np.ndarray,
    dets: list[CameraDetections],
    fixed_names: set[str],
    opt: CalibrationOptions,
    frames: np.ndarray,
    obs: Observations,
    rerun: bool = True,
) -> tuple[BundleResult, dict, np.ndarray]:
    """Drop principal-point offsets, tangential distortion and fx != fy the data do not support.

    With ``principal_point="auto"`` / ``dist_model="auto"`` / ``aspect="auto"``, a camera's
    principal-point offset from the image centre (cx, cy), its tangential terms (p1, p2) and
    the difference fx - fy are tested against zero with Wald chi-square tests on the bundle
    adjustment's covariance; what is not significant at 1 % is fixed (centre, zero, fy = fx)
    and the bundle adjustment is re-run from the solution with the same inliers. Fewer free
    parameters make the remaining ones (rotations above all: a principal point error of 1 px
    tilts a camera by 1/f rad) less noisy.

    Args:
        free: (C, 15) the bundle adjustment's free parameters (updated in place).
        square: (C,) cameras with fy tied to fx (updated in place).

    Returns:
        the (with ``rerun``, re-run) result, ``{camera: model description}`` and the camera
        parameters (C, 15) to re-run from (the result's when nothing changed).
    """
    cam = ba.cam_params
    test_pp = opt.principal_point == "auto"
    test_tan = opt.dist_model == "auto"
    test_aspect = opt.aspect == "auto"
    changed = False
    if test_pp or test_tan or test_aspect:
        cov = camera_covariance(ba, free)
        cam = ba.cam_params.copy()
        for i, d in enumerate(dets):
            if d.name in fixed_names:
                continue
            p = cam[i]
            if test_pp and free[i, 2]:
                centre = np.array([(d.size[0] - 1) / 2, (d.size[1] - 1) / 2])
                chi2 = _wald(p[2:4] - centre, cov[i, 2:4, 2:4])
                logger.info("camera %s: principal-point offset chi2 %.1f", d.name, chi2)
                if chi2 < CHI2_2DOF_1PCT:
                    cam[i, 2:4] = centre
                    free[i, 2:4] = False
                    changed = True
            if test_tan and free[i, 6]:
                chi2 = _wald(p[6:8], cov[i, 6:8, 6:8])
                logger.info("camera %s: tangential distortion chi2 %.1f", d.name, chi2)
                if chi2 < CHI2_2DOF_1PCT:
                    cam[i, 6:8] = 0.0
                    free[i, 6:8] = False
                    changed = True
            if test_aspect and free[i, 0] and free[i, 1]:
                # var(fx - fy) = var fx + var fy - 2 cov(fx, fy)
                c = cov[i, :2, :2]
                chi2 = _wald(np.array([p[0] - p[1]]), (c[0, 0] + c[1, 1] - 2 * c[0, 1])[None, None])
                logger.info("camera %s: fx - fy = %.3f px, chi2 %.1f", d.name, p[0] - p[1], chi2)
                if chi2 < CHI2_1DOF_1PCT:
                    cam[i, :2] = 0.5 * (p[0] + p[1])
                    free[i, 1] = False
                    square[i] = True
                    changed = True
        if changed and rerun:
            ba = _bundle(cam, free, ba.frame_params, frames, obs, opt, ba.f_scale, square, ba)
    models = {
        d.name: _describe_model(free[i], bool(square[i]), d.name in fixed_names)
        for i, d in enumerate(dets)
    }
    return ba, models, cam


def _warn_high(stats: list[CameraStats], warnings: list[str]) -> None:
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


def detection_cache_dir(output: str | Path) -> Path:
    """Folder next to the output that caches detections: ``<output stem>.detections/``."""
    out = Path(output)
    return out.with_name(out.stem + ".detections")


def calibrate(
    sources: Sequence[str | Path],
    board: Board,
    output: str | Path | None = None,
    options: CalibrationOptions | None = None,
) -> CalibrationResult:
    """Detect ``board`` in every frame of every source (video or image folder) and calibrate.

    Detections are cached in :func:`detection_cache_dir` of ``output`` (when given). A camera
    that never sees the board raises :class:`CalibrationError` saying which board the images
    probably show.
    """
    from freipose.io.video import FrameSource

    opt = options or CalibrationOptions()
    if not sources:
        raise CalibrationError("no input videos or image folders given")
    paths = [Path(s) for s in sources]
    stems = [p.stem if p.is_file() else p.name for p in paths]
    dup = sorted({s for s in stems if stems.count(s) > 1})
    if dup:
        raise CalibrationError(
            f"camera names come from the file or folder stems and must be unique; "
            f"{', '.join(dup)} appear(s) more than once"
        )
    cache = detection_cache_dir(output) if output is not None else None
    dets = detect_cameras(paths, board, cache_dir=cache, jobs=opt.jobs, progress=opt.progress)
    for d, p in zip(dets, paths):
        if d.mask.any():
            continue
        with FrameSource(p) as src:
            n = src.num_frames
            idx = np.unique(np.linspace(0, n - 1, min(n, 4)).round().astype(int))
            imgs = [src.read(int(i)) for i in idx]
        hint = diagnose_board(imgs, board)
        raise CalibrationError(
            f"camera {d.name}: the board was never detected in its {d.num_frames} frames ({p})"
            + (f"; {hint}" if hint else "; make sure the camera sees the whole board")
        )
    return calibrate_detections(dets, board, opt)
