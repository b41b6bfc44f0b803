"""From other tools' labels to a :class:`~freipose.io.labels.LabelSet`.

Every format reader produces :class:`SourceLabels` (one recording session of one source,
in the source's own keypoint and camera names; per-camera formats join their tables with
:func:`freipose.labels.views.combine_views`); :func:`build_labelset` maps names onto the
skeleton, checks cameras against the calibration, validates frame indices against the
videos and triangulates 2D labels seen in at least two views.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from freipose.errors import FreiPoseError
from freipose.geometry.camera import CameraRig
from freipose.geometry.triangulation import triangulate_robust
from freipose.io.labels import LabelSet, SessionInfo
from freipose.labels.mapping import NameMapping, resolve_keypoints

log = logging.getLogger(__name__)


class LabelImportError(FreiPoseError):
    """Labels cannot be imported; the message names the file and the problem."""


@dataclass(eq=False)
class SourceLabels:
    """Labels of one session as read from a source, in its own names.

    Attributes:
        source: the file or folder read (for messages).
        session: session (recording) name.
        cameras: (V,) source camera names.
        keypoints: (K,) source keypoint names.
        frame_index: (N,) video frame of each row.
        points2d: (N, V, K, 2) pixels, NaN = unlabeled.
        visible2d: (N, V, K) bool or None ("labeled implies visible").
        points3d: (N, K, 3) mm from the source, or None (then triangulated).
        calibration: the source's own cameras, or None.
        videos: camera -> absolute video path (cameras without one are absent).
        fps: frame rate, if known.
        row_names: (N,) how the source calls each row (image file, frame key), for errors.
        individual: (N,) animal of each row (multi-animal sources), or None.
        positional: the source has no keypoint names (``kp0..``); a skeleton with the same
            number of keypoints names them in order.
        instances: which instances of a source that has several kinds were imported
            (SLEAP: ``user``, ``predicted`` or ``all``), recorded in the labels file.
    """

    source: str
    session: str
    cameras: list[str]
    keypoints: list[str]
    frame_index: np.ndarray
    points2d: np.ndarray
    visible2d: np.ndarray | None = None
    points3d: np.ndarray | None = None
    calibration: CameraRig | None = None
    videos: dict[str, Path] = field(default_factory=dict)
    fps: float | None = None
    row_names: list[str] | None = None
    individual: list[str] | None = None
    positional: bool = False  # keypoints are unnamed: a skeleton of K names names them
    instances: str | None = None


@dataclass(frozen=True)
class ImportOptions:
    """How to turn source labels into a labels file.

    Attributes:
        skeleton_keypoints: the target keypoint order (None: the source's names).
        mapping: keypoint and camera renames.
        calibration: a rig for every session (overrides a source's own cameras).
        ignore_unknown: drop source keypoints that the skeleton lacks instead of failing.
        skip_empty: drop rows without any label instead of failing.
        threshold: RANSAC inlier threshold in pixels for triangulation.
        triangulate: triangulate 2D labels (needs a calibration).
    """

    skeleton_keypoints: tuple[str, ...] | None = None
    mapping: NameMapping = field(default_factory=NameMapping)
    calibration: CameraRig | None = None
    calibration_source: str = "--calibration"
    ignore_unknown: bool = False
    skip_empty: bool = False
    threshold: float = 20.0
    triangulate: bool = True


def _check_rows(src: SourceLabels, skip_empty: bool) -> SourceLabels:
    labeled = np.isfinite(src.points2d).all(-1).any((1, 2))
    if src.points3d is not None:
        labeled |= np.isfinite(src.points3d).all(-1).any(-1)
    if labeled.all():
        return src
    names = src.row_names or [f"frame {f}" for f in src.frame_index]
    empty = [names[i] for i in np.flatnonzero(~labeled)]
    if not skip_empty:
        shown = ", ".join(empty[:5]) + (f" and {len(empty) - 5} more" if len(empty) > 5 else "")
        raise LabelImportError(
            f"{src.source}: {len(empty)} rows have no labeled keypoint (all NaN): {shown}; "
            f"remove them from the source or pass --skip-empty to drop them"
        )
    log.warning("%s: dropping %d rows without labels", src.source, len(empty))
    keep = np.flatnonzero(labeled)
    return dataclasses.replace(
        src,
        frame_index=src.frame_index[keep],
        points2d=src.points2d[keep],
        visible2d=None if src.visible2d is None else src.visible2d[keep],
        points3d=None if src.points3d is None else src.points3d[keep],
        row_names=None if src.row_names is None else [src.row_names[i] for i in keep],
        individual=None if src.individual is None else [src.individual[i] for i in keep],
    )


def check_frames_in_videos(
    session: str, frame_index: np.ndarray, videos: Mapping[str, Path]
) -> float | None:
    """Raise when a frame index lies past the end of a session video (names the file).

    Returns:
        The frame rate of the first video that states one (None: no video does).
    """
    from freipose.io.video import FrameSource, MediaError

    fps = None
    if not len(frame_index):
        return fps
    hi, lo = int(np.max(frame_index)), int(np.min(frame_index))
    if lo < 0:
        raise LabelImportError(f"session {session!r}: negative frame index {lo}")
    for cam, path in sorted(videos.items()):
        try:
            with FrameSource(path) as src:
                n = src.num_frames
                if fps is None and np.isfinite(src.fps) and src.fps > 0:
                    fps = float(src.fps)
        except MediaError as exc:
            raise LabelImportError(f"session {session!r}, camera {cam!r}: {exc}") from exc
        if hi >= n:
            raise LabelImportError(
                f"{path}: labels of session {session!r} use frame {hi}, but the video has only "
                f"{n} frames (0..{n - 1}); the labels belong to another video or it is truncated"
            )
    return fps


def triangulate_labels(
    points2d: np.ndarray, rig: CameraRig, threshold: float = 20.0
) -> tuple[np.ndarray, np.ndarray]:
    """Robust triangulation of labels seen in >= 2 views.

    Args:
        points2d: (N, V, K, 2) pixels in ``rig`` camera order, NaN = unlabeled.
        rig: the V cameras.
        threshold: RANSAC inlier threshold in pixels.

    Returns:
        ``(points3d (N, K, 3), inliers (N, V, K))``; NaN where fewer than two views agree.
    """
    p = np.moveaxis(np.asarray(points2d, dtype=np.float64), 1, 2)  # (N, K, V, 2)
    X, inl = triangulate_robust(p, rig, threshold=threshold, min_inliers=2, refine=True)
    return X, np.moveaxis(inl, 2, 1)


def _relpath(path: Path, base: Path) -> str:
    """``path`` relative to ``base``, symlinks kept (a linked video keeps the link's path)."""
    return os.path.relpath(os.path.abspath(path), os.path.abspath(base))


def _named_keypoints(src: SourceLabels, options: ImportOptions) -> SourceLabels:
    """The source with unnamed (positional) keypoints named by the skeleton, as a copy.

    Args:
        src: the source labels (not changed).
        options: the skeleton keypoints and the mapping.

    Returns:
        ``src`` itself, or a copy with the skeleton's keypoint names.

    Raises:
        LabelImportError: the skeleton has another number of keypoints.
    """
    sk = options.skeleton_keypoints
    if (
        not src.positional
        or sk is None
        or any(k in options.mapping.keypoints for k in src.keypoints)
    ):
        return src
    if len(sk) != len(src.keypoints):
        raise LabelImportError(
            f"{src.source}: the file has {len(src.keypoints)} unnamed keypoints but the "
            f'skeleton has {len(sk)}; name them with a mapping file (kp0 = "NAME", ...)'
        )
    return dataclasses.replace(src, keypoints=list(sk))


def _source_rig(src: SourceLabels, cams: Sequence[str], options: ImportOptions) -> CameraRig | None:
    """The cameras of a source's session: the calibration's (or the source's) cameras it uses.

    Args:
        src: the source labels.
        cams: (V,) its cameras after renaming.
        options: the calibration and the mapping.

    Returns:
        The rig of the source's cameras in calibration order, or None without cameras.

    Raises:
        LabelImportError: a camera is missing from the calibration.
    """
    mapping = options.mapping
    rig = options.calibration if options.calibration is not None else src.calibration
    if rig is None:
        return None
    if options.calibration is None and mapping.cameras:
        rig = CameraRig(tuple(c.replace(name=mapping.camera(c.name)) for c in rig), rig.metadata)
    where = options.calibration_source if options.calibration is not None else src.source
    missing = [c for c in cams if c not in rig.names]
    if missing:
        raise LabelImportError(
            f"{src.source}: cameras {missing} are not in the calibration {where} (its "
            f"cameras: {list(rig.names)}); rename them with --camera-map SOURCE=CAMERA "
            f"or use the matching calibration"
        )
    return rig.subset([c for c in rig.names if c in cams])


@dataclass(frozen=True, eq=False)
class PreparedSource:
    """A source checked against the options, with its names mapped to the targets.

    Attributes:
        src: the source labels (rows checked, keypoints named).
        keypoints: the target keypoints.
        kidx: per source keypoint its target index (None: dropped).
        cameras: (V,) the source's cameras after renaming.
        rig: the cameras of its session, or None.
        videos: camera -> video path.
    """

    src: SourceLabels
    keypoints: tuple[str, ...]
    kidx: list[int | None]
    cameras: list[str]
    rig: CameraRig | None
    videos: dict[str, Path]


def prepare_source(
    src: SourceLabels, options: ImportOptions, keypoints: tuple[str, ...] | None
) -> PreparedSource:
    """Check one source's rows, keypoints, cameras and frames.

    Args:
        src: the source labels (not changed).
        options: the import options.
        keypoints: the target keypoints so far (None: this source's names decide).

    Returns:
        The prepared source.

    Raises:
        LabelImportError / MappingError: empty rows, unknown keypoints, keypoints that
            differ from the first source's, cameras missing from the calibration or
            repeated, frames past a video's end.
    """
    mapping = options.mapping
    src = _named_keypoints(_check_rows(src, options.skip_empty), options)
    target, kidx = resolve_keypoints(
        src.keypoints, mapping, keypoints, src.source, options.ignore_unknown
    )
    if keypoints is not None and target != keypoints:  # a later source without --skeleton
        raise LabelImportError(
            f"{src.source}: keypoints {list(target)} differ from those of the first source "
            f"{list(keypoints)}; pass --skeleton to import sources with different keypoints"
        )
    cams = [mapping.camera(c) for c in src.cameras]
    rig = _source_rig(src, cams, options)
    if len(set(cams)) != len(cams):
        raise LabelImportError(f"{src.source}: cameras {cams} repeat after renaming")
    videos = {mapping.camera(c): Path(p) for c, p in src.videos.items()}
    fps = check_frames_in_videos(src.session, src.frame_index, videos)
    if src.fps is None and fps is not None:
        src = dataclasses.replace(src, fps=fps)
    return PreparedSource(src, target, kidx, cams, rig, videos)


@dataclass(frozen=True)
class SourceArrays:
    """One source's labels in the labels set's camera and keypoint order.

    Attributes:
        points2d: (N, V, K, 2) pixels, NaN = unlabeled.
        visible2d: (N, V, K) bool.
        points3d: (N, K, 3) mm: the source's, else triangulated where possible.
    """

    points2d: np.ndarray
    visible2d: np.ndarray
    points3d: np.ndarray


def source_arrays(
    p: PreparedSource, all_cams: Sequence[str], options: ImportOptions
) -> SourceArrays:
    """Place a source's labels in the target order and triangulate its missing 3D points.

    Args:
        p: the prepared source.
        all_cams: (V,) the cameras of the labels set.
        options: triangulation switch and threshold.

    Returns:
        The source's arrays.
    """
    src, kidx = p.src, p.kidx
    n, v, k = len(src.frame_index), len(all_cams), len(p.keypoints)
    p2 = np.full((n, v, k, 2), np.nan)
    vis = np.zeros((n, v, k), dtype=bool)
    p3 = np.full((n, k, 3), np.nan)
    src_keep = [i for i, t in enumerate(kidx) if t is not None]
    tgt = [kidx[i] for i in src_keep]
    for j, cam in enumerate(p.cameras):
        col = list(all_cams).index(cam)
        block = src.points2d[:, j][:, src_keep]
        p2[:, col, tgt] = block
        finite = np.isfinite(block).all(-1)
        vis[:, col, tgt] = (
            finite if src.visible2d is None else (src.visible2d[:, j][:, src_keep] & finite)
        )
    if src.points3d is not None:
        p3[:, tgt] = src.points3d[:, src_keep]
    if p.rig is not None and options.triangulate:
        cols = [list(all_cams).index(c) for c in p.rig.names]
        todo = ~np.isfinite(p3).all(-1)  # (n, K): no 3D from the source
        if np.any(todo):
            X, _ = triangulate_labels(p2[:, cols], p.rig, options.threshold)
            p3 = np.where(todo[..., None], X, p3)
            n2 = int((np.isfinite(p2[:, cols]).all(-1).sum(1) >= 2)[todo].sum())
            got = int(np.isfinite(X).all(-1)[todo].sum())
            log.info(
                "%s: triangulated %d of %d keypoints labeled in >= 2 views", src.source, got, n2
            )
            _log_reprojection(src, p3, p2[:, cols], p.rig)
    return SourceArrays(p2, vis, p3)


def _log_reprojection(
    src: SourceLabels, points3d: np.ndarray, points2d: np.ndarray, rig: CameraRig
) -> None:
    """Log the reprojection errors of the 2D labels, per animal for multi-animal sources.

    Args:
        src: the source (its name and ``individual``).
        points3d: (N, K, 3) mm.
        points2d: (N, V, K, 2) pixels in ``rig`` order.
        rig: the V cameras.
    """
    from freipose.geometry import reprojection_errors

    err = reprojection_errors(points3d, np.moveaxis(points2d, 1, 2), rig)  # (N, K, V)
    groups = [("", np.ones(len(err), bool))]
    if src.individual is not None:
        names = np.asarray(src.individual, dtype=object)
        groups += [(f" {a}", names == a) for a in dict.fromkeys(src.individual)]
    for name, rows in groups:
        e = err[rows]
        e = e[np.isfinite(e)]
        if len(e):
            log.info(
                "%s%s: reprojection error mean %.2f px, median %.2f px over %d point-views "
                "(%d instants)",
                src.source, name, float(e.mean()), float(np.median(e)), len(e), int(rows.sum()),
            )  # fmt: skip


def _session_info(info: SessionInfo | None, p: PreparedSource, out_dir: Path) -> SessionInfo:
    """The session of a source, merged with what earlier sources gave for the same name.

    Args:
        info: the session so far (None: the first source of this session).
        p: the prepared source.
        out_dir: the folder video paths are made relative to.

    Returns:
        The session's cameras, videos (relative paths) and frame rate.

    Raises:
        LabelImportError: an earlier source of the session has other cameras.
    """
    rig, src = p.rig, p.src
    videos = {c: _relpath(path, out_dir) for c, path in p.videos.items()}
    if info is None:
        return SessionInfo(rig, videos, src.fps, src.instances)
    same_rig = (info.calibration is None) == (rig is None) and (
        rig is None
        or (
            set(info.calibration.names) == set(rig.names)
            and all(info.calibration[c].allclose(rig[c]) for c in rig.names)
        )
    )
    if not same_rig:
        raise LabelImportError(
            f"{src.source}: session {src.session!r} also comes from another source with other "
            f"cameras; give the sources different session names (--session)"
        )
    merged_videos = dict(info.videos)
    merged_videos.update(videos)
    return SessionInfo(
        info.calibration, merged_videos, info.fps or src.fps, info.instances or src.instances
    )


def build_labelset(
    sources: Sequence[SourceLabels], options: ImportOptions, output: str | Path
) -> LabelSet:
    """Merge source labels into one labels set (video paths relative to ``output``'s folder).

    The sources are not changed.

    Args:
        sources: the labels read from the sources, one per session and source.
        options: the import options.
        output: the labels file to be written (its folder anchors the video paths).

    Returns:
        The labels set: rows of all sources in order, cameras in order of appearance.

    Raises:
        LabelImportError / MappingError: unknown keypoints, cameras missing from the
            calibration, empty rows, frames past a video's end (messages name the file).
    """
    if not sources:
        raise LabelImportError("no labels found in the given sources")
    out_dir = Path(os.path.abspath(output)).parent
    prepared: list[PreparedSource] = []
    keypoints = options.skeleton_keypoints
    for src in sources:
        prepared.append(prepare_source(src, options, keypoints))
        keypoints = prepared[-1].keypoints
    all_cams: list[str] = []
    for p in prepared:
        order = list(p.rig.names) if p.rig is not None else p.cameras
        all_cams += [c for c in order if c not in all_cams]
    sessions: dict[str, SessionInfo] = {}
    arrays = []
    for p in prepared:
        arrays.append(source_arrays(p, all_cams, options))
        sessions[p.src.session] = _session_info(sessions.get(p.src.session), p, out_dir)
    any_vis = any(p.src.visible2d is not None for p in prepared)
    any_ind = any(p.src.individual is not None for p in prepared)
    individual = None
    if any_ind:
        individual = np.concatenate(
            [np.asarray(p.src.individual if p.src.individual is not None
                        else [""] * len(p.src.frame_index), dtype=object) for p in prepared]
        )  # fmt: skip
    return LabelSet(
        np.concatenate(
            [np.array([p.src.session] * len(p.src.frame_index), dtype=object) for p in prepared]
        ),
        np.concatenate([np.asarray(p.src.frame_index, dtype=np.int64) for p in prepared]),
        np.concatenate([a.points2d for a in arrays]),
        np.concatenate([a.points3d for a in arrays]),
        tuple(all_cams),
        prepared[0].keypoints,
        sessions,
        np.concatenate([a.visible2d for a in arrays]) if any_vis else None,
        individual,
    )
