"""The calibration pipeline: detections -> intrinsics -> extrinsics -> bundle adjustment -> world.

``calibrate(sources, board, output, options)`` runs everything from videos (detections are
cached next to the output); ``calibrate_detections(detections, board, options)`` starts from
detections (tests, other detectors). The stages are in :mod:`freipose.calibration.stages`,
:mod:`freipose.calibration.model_selection`, :mod:`freipose.calibration.world` and
:mod:`freipose.calibration.stats`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from freipose.calibration.boards import Board
from freipose.calibration.bundle import BundleResult, camera_covariance
from freipose.calibration.bundle_problem import Observations
from freipose.calibration.coverage import CameraCoverage, board_coverage, coverage_warnings
from freipose.calibration.detect import CameraDetections
from freipose.calibration.detect_videos import detect_cameras
from freipose.calibration.diagnose import diagnose_board
from freipose.calibration.extrinsics import CameraGraph
from freipose.calibration.given_intrinsics import given_intrinsics_errors
from freipose.calibration.intrinsics import CalibrationError, IntrinsicsResult, dist_free_mask
from freipose.calibration.model_selection import select_models
from freipose.calibration.options import ASPECT_MODES, PRINCIPAL_POINT_MODES, CalibrationOptions
from freipose.calibration.plausibility import (
    Finding,
    ImplausibleCalibrationError,
    check_plausibility,
    findings_metadata,
    folding_warnings,
)
from freipose.calibration.stages import (
    BoardObservations,
    BundleStart,
    InitialIntrinsics,
    board_observations,
    initial_intrinsics,
    initial_parameters,
    initial_rig,
    refine_board,
    run_bundle,
)
from freipose.calibration.static_frames import merge_static_runs
from freipose.calibration.stats import (
    CameraStats,
    bundle_stats,
    high_error_warnings,
    intrinsic_standard_errors,
    intrinsics_stats,
)
from freipose.calibration.world import WorldFrame, rig_cameras, world_frame
from freipose.geometry import Camera, CameraRig

logger = logging.getLogger(__name__)

__all__ = [
    "CalibrationError",
    "CalibrationResult",
    "ImplausibleCalibrationError",
    "calibrate",
    "calibrate_detections",
    "detection_cache_dir",
    "intrinsics_from",
]


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
        standard_errors: per camera, the standard errors of its free intrinsics (see
            :func:`freipose.calibration.stats.intrinsic_standard_errors`; empty for
            ``intrinsics_only``).
        findings: why the calibration is not physically plausible (only with
            ``accept_implausible``; else such a calibration raises
            :class:`ImplausibleCalibrationError`).
        coverage: per camera, the image regions, depths and floor the board covered
            (empty for ``intrinsics_only``).
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
    standard_errors: dict[str, dict[str, float]] = field(default_factory=dict)
    findings: tuple[Finding, ...] = ()
    coverage: tuple[CameraCoverage, ...] = ()

    def camera_errors(self, camera: int) -> np.ndarray:
        """Final reprojection errors (px) of the inlier detections of camera index ``camera``."""
        if self.bundle is None:
            return np.zeros(0)
        b = self.bundle
        m = (b.obs.cam == camera) & b.inliers
        return b.errors[m]


@dataclass(frozen=True)
class Adjustment:
    """The final bundle adjustment, after board refinement and model selection.

    Attributes:
        bundle: the final adjustment's result.
        obs: the observations it ran on (board points corrected with ``refine_board``).
        models: ``{camera: intrinsics model description}``.
        offsets: (P, 2) mm in-plane corrections of the board points (zeros without
            ``refine_board``).
        free: (C, 15) bool, the final adjustment's free camera parameters.
        square: (C,) bool, cameras whose fy is tied to fx in it.
    """

    bundle: BundleResult
    obs: Observations
    models: dict[str, dict[str, str]]
    offsets: np.ndarray
    free: np.ndarray
    square: np.ndarray


def _common_prefix(
    detections: list[CameraDetections], warnings: list[str]
) -> list[CameraDetections]:
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


def _checked_inputs(
    detections: Sequence[CameraDetections],
    board: Board,
    opt: CalibrationOptions,
    warnings: list[str],
) -> list[CameraDetections]:
    """The detections cut to their common frames, after checking them and the options.

    Raises:
        CalibrationError: no cameras, duplicate names, a camera that never saw the board, or
            an unknown distortion, principal-point or aspect mode.
    """
    dets = _common_prefix(list(detections), warnings) if detections else []
    if not dets:
        raise CalibrationError("no cameras given")
    names = [d.name for d in dets]
    if len(set(names)) != len(names):
        raise CalibrationError(
            f"camera names must be unique (they are the file or folder stems): {names}"
        )
    _check_detected(dets, board)
    dist_free_mask(opt.dist_model)
    if opt.principal_point not in PRINCIPAL_POINT_MODES:
        raise CalibrationError(
            f"unknown principal_point mode {opt.principal_point!r}; expected one of "
            f"{', '.join(PRINCIPAL_POINT_MODES)}"
        )
    if opt.aspect not in ASPECT_MODES:
        raise CalibrationError(
            f"unknown aspect mode {opt.aspect!r}; expected one of {', '.join(ASPECT_MODES)}"
        )
    return dets


def calibrate_detections(
    detections: Sequence[CameraDetections],
    board: Board,
    options: CalibrationOptions | None = None,
) -> CalibrationResult:
    """Calibrate a rig from per-camera detections of ``board`` (synchronized by frame index).

    The same detections give the same calibration to the last bit: the solver's OpenCV calls
    run on one OpenCV thread (OpenCV's multi-threaded ``calibrateCamera`` sums in a varying
    order; the setting is process-wide and given back afterwards), and the cameras'
    intrinsics and board poses are initialised in up to ``options.jobs`` threads instead.

    Args:
        detections: per camera, (F, P, 2) detections of the board's points.
        board: the board.
        options: the options (default: :class:`CalibrationOptions`'s defaults).

    Returns:
        the calibrated rig with everything a report needs.

    Raises:
        CalibrationError: the detections cannot be calibrated (the message says why).
    """
    from freipose.io.video import opencv_threads

    with opencv_threads(1):
        return _calibrate_detections(detections, board, options or CalibrationOptions())


def _merged_static_runs(
    dets: list[CameraDetections], opt: CalibrationOptions
) -> list[CameraDetections]:
    """The detections with each run of frames of a board at rest merged into one view."""
    static = merge_static_runs(dets, opt.origin_frame)
    if static.runs:
        logger.info(
            "the board was at rest in frames %s: each run counts as one view (its mean "
            "corners; %d frames merged)",
            ", ".join(f"{a}-{b}" for a, b, _ in static.runs),
            static.frames_merged,
        )
    return static.detections


def _intrinsics_only(
    dets: list[CameraDetections],
    board: Board,
    intr: InitialIntrinsics,
    warnings: list[str],
) -> CalibrationResult:
    """The result of ``intrinsics_only``: every camera at the origin, looking along z."""
    cams = tuple(
        Camera(d.name, tuple(d.size), intr.Ks[i], intr.dists[i], np.eye(3), np.zeros(3))
        for i, d in enumerate(dets)
    )
    world = "intrinsics only: extrinsics are identity (not calibrated)"
    rig = CameraRig(cams, {"world": world, "calibrated_by": "freipose calib"})
    stats = intrinsics_stats(dets, intr.results)
    warnings.extend(high_error_warnings(stats))
    F = dets[0].num_frames
    return CalibrationResult(
        rig, board, dets, stats, np.full((F, 4, 4), np.nan), world, None, None, warnings,
        intr.results,
    )  # fmt: skip


def _adjust(
    start: BundleStart,
    seen: BoardObservations,
    frames: np.ndarray,
    dets: list[CameraDetections],
    intr: InitialIntrinsics,
    obj: np.ndarray,
    opt: CalibrationOptions,
) -> Adjustment:
    """Bundle adjustment, board refinement and model selection.

    With ``refine_board`` the board is corrected once before the model selection (per-corner
    detector biases otherwise pass for principal-point offsets or tangential distortion),
    and once more with the selected model (that adjustment also serves the selection).
    """
    ba = run_bundle(start.cam0, start.free, start.fr0, frames, seen.obs, opt, square=start.square)
    obs = seen.obs
    offsets = np.zeros((len(obj), 2))
    if opt.refine_board:
        ref = refine_board(
            ba, ba.cam_params, obs, offsets, seen.point_ids, obj, start.free, start.square, opt
        )
        ba, obs, offsets = ref.bundle, ref.obs, ref.offsets
    sel = select_models(
        ba, start.free, start.square, dets, intr.fixed, opt, obs, rerun=not opt.refine_board
    )
    ba = sel.bundle
    if opt.refine_board:
        ref = refine_board(
            ba, sel.start, obs, offsets, seen.point_ids, obj, sel.free, sel.square, opt
        )
        ba, obs, offsets = ref.bundle, ref.obs, ref.offsets
        logger.debug(
            "board points corrected by %.3f mm RMS (max %.3f mm)",
            _rms_offset(offsets),
            float(np.linalg.norm(offsets, axis=1).max()),
        )
    logger.info(
        "bundle adjustment: RMS %.3f -> %.3f px in %.2f s (%d evaluations)",
        ba.initial_rms,
        float(np.sqrt(np.mean(ba.errors[ba.inliers] ** 2))),
        ba.seconds,
        ba.nfev,
    )
    return Adjustment(ba, obs, sel.models, offsets, sel.free, sel.square)


def _rms_offset(offsets: np.ndarray) -> float:
    """RMS length (mm) of the board points' (P, 2) corrections."""
    return float(np.sqrt(np.mean(np.sum(offsets**2, axis=1))))


def _metadata(
    board: Board,
    opt: CalibrationOptions,
    world: WorldFrame,
    adj: Adjustment,
    quality: _Quality,
) -> dict[str, Any]:
    """The calibration file's metadata."""
    ba = adj.bundle
    rms_all = float(np.sqrt(np.mean(ba.errors[ba.inliers] ** 2)))
    metadata: dict[str, Any] = {
        "world": world.description,
        "calibrated_by": "freipose calib",
        "board": board.to_dict(),
        "reprojection_rms_px": round(rms_all, 4),
        "distortion_model": opt.dist_model,
        "intrinsics_model": adj.models,
        "view_weights": bool(opt.view_weights),
    }
    if opt.refine_board:
        metadata["board_point_corrections_rms_mm"] = round(_rms_offset(adj.offsets), 4)
    if opt.origin_frame is not None:
        metadata["origin_frame"] = int(opt.origin_frame)
    if world.up is not None:
        metadata.update(world.up.metadata())
    metadata["intrinsics_standard_errors"] = {
        cam: {k: float(f"{v:.4g}") for k, v in se.items()}
        for cam, se in quality.standard_errors.items()
        if se
    }
    if quality.findings:
        metadata["suspect"] = findings_metadata(quality.findings)
    return metadata


@dataclass(frozen=True)
class _Quality:
    """The final adjustment's intrinsic standard errors and plausibility findings."""

    standard_errors: dict[str, dict[str, float]]
    findings: tuple[Finding, ...]


def _quality(
    dets: list[CameraDetections],
    board: Board,
    adj: Adjustment,
    intr: InitialIntrinsics,
    opt: CalibrationOptions,
) -> _Quality:
    """Standard errors and plausibility of the final adjustment.

    Raises:
        ImplausibleCalibrationError: a finding, without ``opt.accept_implausible``.
    """
    names = [d.name for d in dets]
    cov = camera_covariance(adj.bundle, adj.free, adj.square)
    se = intrinsic_standard_errors(cov, adj.free, adj.square, names)
    diag = float(np.hypot(*board.size_mm))
    sizes = [tuple(d.size) for d in dets]
    given = given_intrinsics_errors(names, adj.bundle, adj.free, adj.square, intr.fixed, opt)
    own = {n: r.rms for n, r in intr.results.items()}
    findings = check_plausibility(names, sizes, adj.bundle, diag, se, intr.fixed, given, own)
    if findings and not opt.accept_implausible:
        raise ImplausibleCalibrationError(findings)
    return _Quality(se, findings)


def _calibrate_detections(
    detections: Sequence[CameraDetections], board: Board, opt: CalibrationOptions
) -> CalibrationResult:
    warnings: list[str] = []
    dets = _merged_static_runs(_checked_inputs(detections, board, opt, warnings), opt)
    obj = board.object_points
    intr = initial_intrinsics(dets, obj, opt)
    warnings.extend(intr.warnings)
    if opt.intrinsics_only:
        return _intrinsics_only(dets, board, intr, warnings)
    rig0 = initial_rig(dets, obj, intr, opt.jobs)
    seen = board_observations(dets, obj, rig0.frames)
    start = initial_parameters(dets, intr, rig0, opt)
    adj = _adjust(start, seen, rig0.frames, dets, intr, obj, opt)
    quality = _quality(dets, board, adj, intr, opt)
    names = [d.name for d in dets]
    warnings.extend(folding_warnings(names, [tuple(d.size) for d in dets], adj.bundle))
    world = world_frame(adj.bundle, dets[0].num_frames, names, opt.origin_frame, opt.up)
    if world.up is None:
        warnings.append(
            f"the world is camera {names[0]}'s frame and its up direction is unknown (later "
            f"steps estimate it from the labeled animal or assume z): pass --origin-frame N (a "
            f"frame with the board on the floor) or --up X,Y,Z, or set it with freipose calib up"
        )
    cams = rig_cameras(dets, adj.bundle, world.cameras)
    stats = bundle_stats(dets, adj.bundle, adj.obs, intr.results)
    warnings.extend(high_error_warnings(stats))
    rig = CameraRig(cams, _metadata(board, opt, world, adj, quality))
    coverage = board_coverage(dets, rig, world.board_poses, obj, world.up)
    warnings.extend(coverage_warnings(coverage))
    return CalibrationResult(
        rig, board, dets, stats, world.board_poses, world.description, rig0.graph, adj.bundle,
        warnings, intr.results, adj.offsets if opt.refine_board else None,
        quality.standard_errors, quality.findings, coverage,
    )  # fmt: skip


def detection_cache_dir(output: str | Path) -> Path:
    """Folder next to the output that caches detections: ``<output stem>.detections/``.

    An output named ``.`` or ``..`` (a JARVIS folder) is taken by its absolute name.
    """
    out = Path(output)
    if out.name in ("", ".", ".."):
        out = out.resolve()
    return out.with_name(out.stem + ".detections")


def calibrate(
    sources: Sequence[str | Path],
    board: Board,
    output: str | Path | None = None,
    options: CalibrationOptions | None = None,
    board_file: str | Path | None = None,
) -> CalibrationResult:
    """Detect ``board`` in every frame of every source (video or image folder) and calibrate.

    Detections are cached in :func:`detection_cache_dir` of ``output`` (when given). A camera
    that never sees the board raises :class:`CalibrationError` saying which board the images
    probably show.

    Args:
        sources: one video file or image folder per camera (its stem names the camera).
        board: the board.
        output: the calibration file to be written (names the detection cache); ``None``:
            no cache.
        options: the options (default: :class:`CalibrationOptions`'s defaults).
        board_file: the board's file, named in the hint when the board is never found.

    Returns:
        the calibrated rig with everything a report needs.

    Raises:
        CalibrationError: no sources, duplicate camera names, or the detections cannot be
            calibrated.
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
        hint = diagnose_board(imgs, board, None if board_file is None else str(board_file))
        raise CalibrationError(
            f"camera {d.name}: the board was never detected in its {d.num_frames} frames ({p})"
            + (f"; {hint}" if hint else "; make sure the camera sees the whole board")
        )
    return calibrate_detections(dets, board, opt)


def _intrinsic_source(folder: Path, camera: str) -> Path:
    """The video file or image folder in ``folder`` named after ``camera``.

    Raises:
        CalibrationError: there is none, or more than one.
    """
    from freipose.io.video import VIDEO_SUFFIXES

    found = [p for p in sorted(folder.iterdir()) if p.stem == camera or p.name == camera]
    found = [p for p in found if p.is_dir() or p.suffix.lower() in VIDEO_SUFFIXES]
    if len(found) != 1:
        what = "no video or image folder" if not found else f"{len(found)} candidates"
        raise CalibrationError(
            f"--intrinsics-from {folder}: {what} for camera {camera} (expected "
            f"{folder / camera}.mp4 or another video, or an image folder {folder / camera}/, "
            f"named like the camera's board video)"
        )
    return found[0]


def intrinsics_from(
    source: str | Path,
    cameras: Sequence[str],
    board: Board,
    options: CalibrationOptions | None = None,
) -> CameraRig:
    """Every camera's intrinsics from a separate recording, for ``fixed_intrinsics``.

    Args:
        source: a calibration file (any format :func:`freipose.io.calibration.load_calibration`
            reads) holding the cameras by name, or a folder with one video or image folder of
            ``board`` per camera, named after it (its intrinsics are calibrated first).
        cameras: the camera names.
        board: the board of the intrinsic recordings.
        options: the options of the intrinsics calibration (``dist_model``,
            ``principal_point``, ``max_views``, ``jobs``, ``progress``).

    Returns:
        a rig with the cameras' K and distortion (extrinsics not meaningful).

    Raises:
        CalibrationError: a camera that the file or folder does not have.
    """
    from dataclasses import replace

    from freipose.io.calibration import load_calibration

    src = Path(source)
    if not src.is_dir():
        rig = load_calibration(src)
        missing = [c for c in cameras if c not in rig]
        if missing:
            raise CalibrationError(
                f"--intrinsics-from {src}: camera(s) {', '.join(missing)} are not in the file "
                f"(it has {', '.join(rig.names)}); name the videos like its cameras, or give "
                f"a folder of per-camera intrinsic recordings"
            )
        return rig.subset(list(cameras))
    opt = replace(options or CalibrationOptions(), intrinsics_only=True, fixed_intrinsics=None)
    paths = [_intrinsic_source(src, c) for c in cameras]
    cams = []
    for c, p in zip(cameras, paths):
        res = calibrate([p], board, None, opt)
        cam = res.rig[0]
        cams.append(Camera(c, cam.size, cam.K, cam.dist, np.eye(3), np.zeros(3)))
        logger.info("camera %s: intrinsics from %s, RMS %.3f px", c, p, res.stats[0].rms)
    return CameraRig(tuple(cams), {"intrinsics_from": str(src)})
