"""The calibration's stages from detections to the first bundle adjustment.

Each stage is a function of the previous stages' results that returns a small frozen
dataclass: :func:`initial_intrinsics` (per-camera K and distortion), :func:`initial_rig`
(board poses, camera graph, initial extrinsics), :func:`board_observations` (every detection
in a frame with a board pose), :func:`initial_parameters` (the bundle adjustment's starting
point and free parameters), :func:`run_bundle` and :func:`refine_board` (the board points'
in-plane corrections and the adjustment that follows them).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from freipose.calibration.bundle import BundleResult, board_point_offsets, bundle_adjust
from freipose.calibration.bundle_problem import Observations
from freipose.calibration.detect import CameraDetections
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
from freipose.calibration.options import CalibrationOptions
from freipose.calibration.params import (
    CAM_PARAMS,
    DIST,
    EXTRINSICS,
    FOCAL,
    FRAME_PARAMS,
    FRAME_RVEC,
    FRAME_TVEC,
    PINHOLE,
    PRINCIPAL,
    RVEC,
    TVEC,
)
from freipose.geometry.transforms import matrix_to_rodrigues

_In = TypeVar("_In")
_Out = TypeVar("_Out")

logger = logging.getLogger(__name__)

__all__ = [
    "BoardObservations",
    "BoardRefinement",
    "BundleStart",
    "InitialIntrinsics",
    "InitialRig",
    "board_observations",
    "initial_intrinsics",
    "initial_parameters",
    "initial_rig",
    "map_cameras",
    "refine_board",
    "run_bundle",
]


def map_cameras(fn: Callable[[_In], _Out], items: Sequence[_In], jobs: int | None) -> list[_Out]:
    """``[fn(x) for x in items]`` in up to ``jobs`` threads (default: CPU count).

    OpenCV releases the interpreter while it computes, so the threads run in parallel.

    Args:
        fn: the function applied to every item.
        items: the items, one per camera.
        jobs: the most threads; ``None``: the CPU count.

    Returns:
        ``fn``'s results in the order of ``items``.
    """
    n = min(len(items), jobs or os.cpu_count() or 1)
    if n <= 1:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(n) as ex:
        return list(ex.map(fn, items))


@dataclass(frozen=True)
class InitialIntrinsics:
    """Every camera's starting intrinsics.

    Attributes:
        Ks: (3, 3) camera matrix per camera, in detection order.
        dists: (5,) distortion k1 k2 p1 p2 k3 per camera.
        fixed: names of the cameras whose intrinsics are given (kept fixed).
        results: per calibrated camera, the intrinsics calibration's result.
        warnings: messages for the user about weakly constrained intrinsics.
    """

    Ks: list[np.ndarray]
    dists: list[np.ndarray]
    fixed: frozenset[str]
    results: dict[str, IntrinsicsResult]
    warnings: list[str]


def _fixed_cameras(dets: Sequence[CameraDetections], opt: CalibrationOptions) -> frozenset[str]:
    """Names of the cameras whose intrinsics ``opt.fixed_intrinsics`` gives.

    Raises:
        CalibrationError: a camera is missing from the fixed rig or has another image size.
    """
    fixed = opt.fixed_intrinsics
    if fixed is None:
        return frozenset()
    for d in dets:
        if d.name not in fixed:
            raise CalibrationError(
                f"camera {d.name} is not in the --fix-intrinsics file (it has "
                f"{', '.join(fixed.names)}); name the videos like its cameras"
            )
        cam = fixed[d.name]
        if tuple(cam.size) != tuple(d.size):
            raise CalibrationError(
                f"camera {d.name}: the --fix-intrinsics file is for {cam.size[0]}x"
                f"{cam.size[1]} images but the video is {d.size[0]}x{d.size[1]}"
            )
    return frozenset(d.name for d in dets)


def initial_intrinsics(
    dets: Sequence[CameraDetections], obj: np.ndarray, opt: CalibrationOptions
) -> InitialIntrinsics:
    """Calibrate every camera's intrinsics on its own (or take them from the fixed rig).

    Args:
        dets: per camera, (F, P, 2) detections.
        obj: (P, 3) board points (mm).
        opt: the options (``fixed_intrinsics``, ``dist_model``, ``max_views``,
            ``principal_point``, ``jobs``).

    Returns:
        the cameras' K and distortion, in detection order.
    """
    fixed = _fixed_cameras(dets, opt)
    to_calibrate = [d for d in dets if d.name not in fixed]
    results = map_cameras(
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
    Ks, dists, warnings = [], [], []
    for d in dets:
        if d.name in fixed and opt.fixed_intrinsics is not None:
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
        logger.debug(
            "camera %s: intrinsics from %d views, RMS %.3f px, f = %.1f, %.1f",
            d.name,
            len(res.frames),
            res.rms,
            res.K[0, 0],
            res.K[1, 1],
        )
    return InitialIntrinsics(Ks, dists, fixed, intr, warnings)


@dataclass(frozen=True)
class InitialRig:
    """The rig's starting extrinsics and board poses.

    Attributes:
        T_world: (C, 4, 4) world→camera of every camera (the graph's root camera's frame).
        graph: the camera graph the extrinsics were chained along.
        board_poses: (F, 4, 4) board→world per frame, NaN where no camera gives one.
        frames: (K,) the frames with a board pose, ascending.
    """

    T_world: np.ndarray
    graph: CameraGraph
    board_poses: np.ndarray
    frames: np.ndarray


def initial_rig(
    dets: Sequence[CameraDetections],
    obj: np.ndarray,
    intr: InitialIntrinsics,
    jobs: int | None,
) -> InitialRig:
    """Chain the cameras by the board poses they see in the same frames.

    Args:
        dets: per camera, (F, P, 2) detections.
        obj: (P, 3) board points (mm).
        intr: the cameras' intrinsics.
        jobs: threads that estimate the cameras' board poses.

    Returns:
        the initial extrinsics, camera graph and board poses.

    Raises:
        CalibrationError: a camera has no frame with a consistent board pose.
    """
    names = [d.name for d in dets]
    Ks, dists = intr.Ks, intr.dists
    poses = np.stack(
        map_cameras(
            lambda i: board_poses_per_camera(dets[i].points, obj, Ks[i], dists[i])[0],
            range(len(dets)),
            jobs,
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
    return InitialRig(T_world, graph, B0, frames)


@dataclass(frozen=True)
class BoardObservations:
    """Every detection in a frame with a board pose.

    Attributes:
        obs: the observations (N of them; ``frame`` indexes the frames with a board pose).
        point_ids: (N,) the board point of every observation.
    """

    obs: Observations
    point_ids: np.ndarray


def board_observations(
    dets: Sequence[CameraDetections], obj: np.ndarray, frames: np.ndarray
) -> BoardObservations:
    """Collect the detections of the frames in ``frames``, camera by camera.

    Args:
        dets: per camera, (F, P, 2) detections.
        obj: (P, 3) board points (mm).
        frames: (K,) frames with a board pose, ascending.

    Returns:
        the observations and their board point ids.
    """
    frame_pos = np.full(dets[0].num_frames, -1)
    frame_pos[frames] = np.arange(len(frames))
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
    return BoardObservations(obs, np.concatenate(pt_i))


@dataclass(frozen=True)
class BundleStart:
    """The bundle adjustment's starting point.

    Attributes:
        cam0: (C, 15) camera parameters fx fy cx cy k1 k2 p1 p2 k3 rvec t.
        free: (C, 15) bool, the parameters the adjustment estimates.
        square: (C,) bool, cameras whose fy is tied to fx.
        fr0: (K, 6) board→world rvec t of every frame with a board pose.
    """

    cam0: np.ndarray
    free: np.ndarray
    square: np.ndarray
    fr0: np.ndarray


def initial_parameters(
    dets: Sequence[CameraDetections],
    intr: InitialIntrinsics,
    rig0: InitialRig,
    opt: CalibrationOptions,
) -> BundleStart:
    """Pack the initial intrinsics, extrinsics and board poses into parameter arrays.

    Args:
        dets: per camera, (F, P, 2) detections.
        intr: the cameras' intrinsics.
        rig0: the initial extrinsics and board poses.
        opt: the options (``dist_model``, ``principal_point``, ``aspect``).

    Returns:
        the starting parameters and which of them are free.
    """
    Ks, dists, T_world, graph = intr.Ks, intr.dists, rig0.T_world, rig0.graph
    free_dist = dist_free_mask(opt.dist_model)
    C = len(dets)
    cam0 = np.zeros((C, CAM_PARAMS))
    free = np.zeros((C, CAM_PARAMS), bool)
    square = np.zeros(C, bool)  # fy tied to fx
    for i, d in enumerate(dets):
        K = Ks[i]
        cam0[i, PINHOLE] = (K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        cam0[i, DIST] = dists[i]
        cam0[i, RVEC] = matrix_to_rodrigues(T_world[i, :3, :3])
        cam0[i, TVEC] = T_world[i, :3, 3]
        if d.name not in intr.fixed:
            free[i, PINHOLE] = True
            free[i, DIST] = free_dist
            if opt.principal_point == "centre":
                cam0[i, PRINCIPAL] = ((d.size[0] - 1) / 2, (d.size[1] - 1) / 2)
                free[i, PRINCIPAL] = False
            if opt.aspect == "square":
                cam0[i, FOCAL] = 0.5 * (K[0, 0] + K[1, 1])
                free[i, 1] = False
                square[i] = True
        if i != graph.root:
            free[i, EXTRINSICS] = True
    B0 = rig0.board_poses
    fr0 = np.zeros((len(rig0.frames), FRAME_PARAMS))
    for k, f in enumerate(rig0.frames):
        fr0[k, FRAME_RVEC] = matrix_to_rodrigues(B0[f, :3, :3])
        fr0[k, FRAME_TVEC] = B0[f, :3, 3]
    return BundleStart(cam0, free, square, fr0)


def run_bundle(
    cam: np.ndarray,
    free: np.ndarray,
    fr: np.ndarray,
    frames: np.ndarray,
    obs: Observations,
    opt: CalibrationOptions,
    start_scale: float = 1.0,
    square: np.ndarray | None = None,
    prev: BundleResult | None = None,
) -> BundleResult:
    """Bundle adjustment with the options' loss, rejection, solver and view weighting.

    Args:
        cam: (C, 15) starting camera parameters.
        free: (C, 15) bool, the free camera parameters.
        fr: (K, 6) starting board poses.
        frames: (K,) the video frame of every board pose.
        obs: the observations (N).
        opt: the options (``loss``, ``f_scale``, ``outlier_px``, ``solver``,
            ``view_weights``).
        start_scale: the robust loss's starting scale (px).
        square: (C,) bool, cameras whose fy is tied to fx.
        prev: a result on the same observations: its inliers and view weights are the
            starting ones.

    Returns:
        the adjusted parameters and diagnostics.
    """
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


@dataclass(frozen=True)
class BoardRefinement:
    """A bundle adjustment on corrected board points.

    Attributes:
        bundle: the adjustment's result.
        obs: the observations with the corrected board points.
        offsets: (P, 2) mm in-plane corrections of the board points, all rounds together.
    """

    bundle: BundleResult
    obs: Observations
    offsets: np.ndarray


def refine_board(
    ba: BundleResult,
    start: np.ndarray,
    obs: Observations,
    offsets: np.ndarray,
    point_ids: np.ndarray,
    obj: np.ndarray,
    free: np.ndarray,
    square: np.ndarray,
    opt: CalibrationOptions,
) -> BoardRefinement:
    """Correct the board points in the board plane by ``ba``'s residuals and adjust again.

    Args:
        ba: the last adjustment (its board poses, robust scale, inliers and view weights
            are the new one's start).
        start: (C, 15) camera parameters to start from.
        obs: the observations ``ba`` was run on.
        offsets: (P, 2) mm corrections of the earlier rounds (zeros at first).
        point_ids: (N,) the board point of every observation.
        obj: (P, 3) printed board points (mm).
        free: (C, 15) bool, the free camera parameters.
        square: (C,) bool, cameras whose fy is tied to fx.
        opt: the options.

    Returns:
        the new adjustment, its observations and the corrections so far.
    """
    offsets = offsets + board_point_offsets(ba, point_ids, len(obj))
    pts = obj.copy()
    pts[:, :2] += offsets
    obs = Observations(obs.cam, obs.frame, pts[point_ids], obs.uv)
    new = run_bundle(start, free, ba.frame_params, ba.frames, obs, opt, ba.f_scale, square, ba)
    return BoardRefinement(new, obs, offsets)
