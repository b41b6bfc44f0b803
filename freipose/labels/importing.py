"""From other tools' labels to a :class:`~freipose.io.labels.LabelSet`.

Every format reader produces :class:`SourceLabels` (one recording session of one source,
in the source's own keypoint and camera names); :func:`build_labelset` maps names onto the
skeleton, checks cameras against the calibration, validates frame indices against the
videos and triangulates 2D labels seen in at least two views.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from freipose.geometry.camera import CameraRig
from freipose.geometry.triangulation import triangulate_robust
from freipose.io.labels import LabelSet, SessionInfo
from freipose.labels.mapping import NameMapping, resolve_keypoints

log = logging.getLogger(__name__)


class LabelImportError(ValueError):
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


_DIGITS = re.compile(r"(\d+)")


def frame_from_name(name: str, source: str) -> int:
    """The frame index in an image file name: the last digit run of its stem (img0123 -> 123)."""
    stem = Path(str(name).replace("\\", "/")).stem
    runs = _DIGITS.findall(stem)
    if not runs:
        raise LabelImportError(
            f"{source}: cannot tell the frame index of {name!r}; image names must contain the "
            f"video frame number (e.g. img0123.png)"
        )
    return int(runs[-1])


def match_camera(name: str, cameras: Sequence[str]) -> tuple[str, str] | None:
    """Find a camera name inside a folder/file name: exact, or a ``_ - .`` separated token.

    Returns ``(camera, rest)`` (rest: the name without the camera token, e.g. the session),
    the longest match winning; None when no camera matches.
    """
    best: tuple[str, str] | None = None
    for cam in cameras:
        if name == cam:
            return cam, ""
        pat = re.compile(rf"(^|[_\-. ]){re.escape(cam)}($|[_\-. ])")
        m = pat.search(name)
        if m and (best is None or len(cam) > len(best[0])):
            rest = (name[: m.start()] + m.group(1) + name[m.end() :]).strip("_-. ")
            rest = re.sub(r"[_\-. ]{2,}", "_", rest)
            best = (cam, rest)
    return best


def camera_from_name(
    name: str,
    source: object,
    calibration: CameraRig | None,
    mapping: NameMapping,
    kind: str = "file",
) -> tuple[str, str]:
    """``(camera, session)`` of a per-camera source file/folder called ``name``.

    A name in ``--camera-map`` is kept as the camera; else, with a calibration, the
    calibration camera inside the name (``run1_cam0`` -> ``("cam0", "run1")``); else the
    name itself. The session is ``""`` when the name does not tell it.

    Raises:
        LabelImportError: with a calibration, the name contains none of its cameras.
    """
    if name in mapping.cameras or calibration is None:
        return name, ""
    m = match_camera(name, calibration.names)
    if m is None:
        raise LabelImportError(
            f"{source}: {kind} {name!r} names none of the calibration cameras "
            f"{list(calibration.names)}; name {kind}s <session>_<camera> or pass "
            f"--camera-map {name}=CAMERA"
        )
    return m


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
    return SourceLabels(
        src.source,
        src.session,
        src.cameras,
        src.keypoints,
        src.frame_index[keep],
        src.points2d[keep],
        None if src.visible2d is None else src.visible2d[keep],
        None if src.points3d is None else src.points3d[keep],
        src.calibration,
        src.videos,
        src.fps,
        None if src.row_names is None else [src.row_names[i] for i in keep],
        None if src.individual is None else [src.individual[i] for i in keep],
        src.positional,
    )


def check_frames_in_videos(
    session: str, frame_index: np.ndarray, videos: Mapping[str, Path]
) -> None:
    """Raise when a frame index lies past the end of a session video (names the file)."""
    from freipose.io.video import FrameSource, MediaError

    if not len(frame_index):
        return
    hi, lo = int(np.max(frame_index)), int(np.min(frame_index))
    if lo < 0:
        raise LabelImportError(f"session {session!r}: negative frame index {lo}")
    for cam, path in sorted(videos.items()):
        try:
            with FrameSource(path) as src:
                n = src.num_frames
        except MediaError as exc:
            raise LabelImportError(f"session {session!r}, camera {cam!r}: {exc}") from exc
        if hi >= n:
            raise LabelImportError(
                f"{path}: labels of session {session!r} use frame {hi}, but the video has only "
                f"{n} frames (0..{n - 1}); the labels belong to another video or it is truncated"
            )


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
    return os.path.relpath(Path(path).resolve(), Path(base).resolve())


def build_labelset(
    sources: Sequence[SourceLabels], options: ImportOptions, output: str | Path
) -> LabelSet:
    """Merge source labels into one labels set (video paths relative to ``output``'s folder).

    Raises:
        LabelImportError / MappingError: unknown keypoints, cameras missing from the
            calibration, empty rows, frames past a video's end (messages name the file).
    """
    if not sources:
        raise LabelImportError("no labels found in the given sources")
    out_dir = Path(output).resolve().parent
    mapping = options.mapping
    prepared = []
    keypoints: tuple[str, ...] | None = options.skeleton_keypoints
    for src in sources:
        src = _check_rows(src, options.skip_empty)
        sk = options.skeleton_keypoints
        if (
            src.positional
            and sk is not None
            and not any(k in mapping.keypoints for k in src.keypoints)
        ):
            if len(sk) != len(src.keypoints):
                raise LabelImportError(
                    f"{src.source}: the file has {len(src.keypoints)} unnamed keypoints but the "
                    f'skeleton has {len(sk)}; name them with a mapping file (kp0 = "NAME", ...)'
                )
            src.keypoints = list(sk)
        target, kidx = resolve_keypoints(
            src.keypoints, mapping, keypoints, src.source, options.ignore_unknown
        )
        if keypoints is None:
            keypoints = target
        elif target != keypoints:  # a later source without --skeleton: must agree
            raise LabelImportError(
                f"{src.source}: keypoints {list(target)} differ from those of the first source "
                f"{list(keypoints)}; pass --skeleton to import sources with different keypoints"
            )
        cams = [mapping.camera(c) for c in src.cameras]
        rig = options.calibration if options.calibration is not None else src.calibration
        if rig is not None:
            if options.calibration is None and mapping.cameras:
                rig = CameraRig(
                    tuple(c.replace(name=mapping.camera(c.name)) for c in rig), rig.metadata
                )
            where = options.calibration_source if options.calibration is not None else src.source
            missing = [c for c in cams if c not in rig.names]
            if missing:
                raise LabelImportError(
                    f"{src.source}: cameras {missing} are not in the calibration {where} (its "
                    f"cameras: {list(rig.names)}); rename them with --camera-map SOURCE=CAMERA "
                    f"or use the matching calibration"
                )
            rig = rig.subset([c for c in rig.names if c in cams])
        if len(set(cams)) != len(cams):
            raise LabelImportError(f"{src.source}: cameras {cams} repeat after renaming")
        videos = {mapping.camera(c): Path(p) for c, p in src.videos.items()}
        check_frames_in_videos(src.session, src.frame_index, videos)
        prepared.append((src, kidx, cams, rig, videos))
    assert keypoints is not None
    all_cams: list[str] = []
    for _, _, cams, rig, _ in prepared:
        order = list(rig.names) if rig is not None else cams
        all_cams += [c for c in order if c not in all_cams]
    k = len(keypoints)
    v = len(all_cams)
    sessions: dict[str, SessionInfo] = {}
    parts_sess, parts_fi, parts_p2, parts_p3, parts_vis = [], [], [], [], []
    any_vis = any(s.visible2d is not None for s, *_ in prepared)
    for src, kidx, cams, rig, videos in prepared:
        n = len(src.frame_index)
        p2 = np.full((n, v, k, 2), np.nan)
        vis = np.zeros((n, v, k), dtype=bool)
        p3 = np.full((n, k, 3), np.nan)
        src_keep = [i for i, t in enumerate(kidx) if t is not None]
        tgt = [kidx[i] for i in src_keep]
        for j, cam in enumerate(cams):
            col = all_cams.index(cam)
            block = src.points2d[:, j][:, src_keep]
            p2[:, col, tgt] = block
            finite = np.isfinite(block).all(-1)
            vis[:, col, tgt] = (
                finite if src.visible2d is None else (src.visible2d[:, j][:, src_keep] & finite)
            )
        if src.points3d is not None:
            p3[:, tgt] = src.points3d[:, src_keep]
        if rig is not None and options.triangulate:
            cols = [all_cams.index(c) for c in rig.names]
            todo = ~np.isfinite(p3).all(-1)  # (n, K): no 3D from the source
            if np.any(todo):
                X, _ = triangulate_labels(p2[:, cols], rig, options.threshold)
                p3 = np.where(todo[..., None], X, p3)
                n2 = int((np.isfinite(p2[:, cols]).all(-1).sum(1) >= 2)[todo].sum())
                got = int(np.isfinite(X).all(-1)[todo].sum())
                log.info(
                    "%s: triangulated %d of %d keypoints labeled in >= 2 views",
                    src.source,
                    got,
                    n2,
                )
        name = src.session
        if name in sessions:
            info = sessions[name]
            same_rig = (info.calibration is None) == (rig is None) and (
                rig is None
                or (
                    set(info.calibration.names) == set(rig.names)
                    and all(info.calibration[c].allclose(rig[c]) for c in rig.names)
                )
            )
            if not same_rig:
                raise LabelImportError(
                    f"{src.source}: session {name!r} also comes from another source with other "
                    f"cameras; give the sources different session names (--session)"
                )
            merged_videos = dict(info.videos)
            merged_videos.update({c: _relpath(p, out_dir) for c, p in videos.items()})
            sessions[name] = SessionInfo(info.calibration, merged_videos, info.fps or src.fps)
        else:
            sessions[name] = SessionInfo(
                rig, {c: _relpath(p, out_dir) for c, p in videos.items()}, src.fps
            )
        parts_sess.append(np.array([name] * n, dtype=object))
        parts_fi.append(np.asarray(src.frame_index, dtype=np.int64))
        parts_p2.append(p2)
        parts_p3.append(p3)
        parts_vis.append(vis)
    return LabelSet(
        np.concatenate(parts_sess),
        np.concatenate(parts_fi),
        np.concatenate(parts_p2),
        np.concatenate(parts_p3),
        tuple(all_cams),
        keypoints,
        sessions,
        np.concatenate(parts_vis) if any_vis else None,
    )


@dataclass(eq=False)
class ViewTable:
    """2D labels of one camera: rows keyed by (frame, individual)."""

    source: str
    camera: str
    keypoints: list[str]
    frame_index: np.ndarray  # (N,)
    points2d: np.ndarray  # (N, K, 2)
    row_names: list[str]
    individual: list[str] | None = None
    visible2d: np.ndarray | None = None  # (N, K)


def combine_views(
    session: str,
    views: Sequence[ViewTable],
    calibration: CameraRig | None = None,
    videos: Mapping[str, Path] | None = None,
    fps: float | None = None,
) -> SourceLabels:
    """Join per-camera tables of one session into rows keyed by (frame, individual).

    Raises:
        LabelImportError: two tables for one camera, or tables with different keypoints.
    """
    cams = [vt.camera for vt in views]
    dup = sorted({c for c in cams if cams.count(c) > 1})
    if dup:
        srcs = [vt.source for vt in views if vt.camera in dup]
        raise LabelImportError(
            f"session {session!r}: several sources {srcs} map to camera(s) {dup}; name "
            f"folders/files <session>_<camera> or map them with --camera-map"
        )
    kps = list(views[0].keypoints)
    for vt in views[1:]:
        if list(vt.keypoints) != kps:
            raise LabelImportError(
                f"{vt.source}: keypoints {list(vt.keypoints)} differ from {kps} in "
                f"{views[0].source}; all cameras of a session must label the same keypoints"
            )
    keys: dict[tuple[int, str], int] = {}
    names: list[str] = []
    for vt in views:
        for r, f in enumerate(vt.frame_index):
            ind = vt.individual[r] if vt.individual is not None else ""
            key = (int(f), ind)
            if key not in keys:
                keys[key] = len(keys)
                names.append(vt.row_names[r])
    order = sorted(keys, key=lambda kv: (kv[0], kv[1]))
    pos = {key: i for i, key in enumerate(order)}
    n, v, k = len(order), len(views), len(kps)
    p2 = np.full((n, v, k, 2), np.nan)
    any_vis = any(vt.visible2d is not None for vt in views)
    vis = np.zeros((n, v, k), dtype=bool)
    for j, vt in enumerate(views):
        seen = set()
        for r, f in enumerate(vt.frame_index):
            ind = vt.individual[r] if vt.individual is not None else ""
            i = pos[(int(f), ind)]
            if i in seen:
                raise LabelImportError(
                    f"{vt.source}: frame {int(f)}"
                    + (f" of {ind!r}" if ind else "")
                    + f" is labeled twice ({vt.row_names[r]})"
                )
            seen.add(i)
            p2[i, j] = vt.points2d[r]
            fin = np.isfinite(vt.points2d[r]).all(-1)
            vis[i, j] = fin if vt.visible2d is None else (vt.visible2d[r] & fin)
    row_names = [names[keys[key]] for key in order]
    has_ind = any(vt.individual is not None for vt in views)
    return SourceLabels(
        source=", ".join(dict.fromkeys(vt.source for vt in views)),
        session=session,
        cameras=cams,
        keypoints=kps,
        frame_index=np.array([key[0] for key in order], dtype=np.int64),
        points2d=p2,
        visible2d=vis if any_vis else None,
        calibration=calibration,
        videos=dict(videos or {}),
        fps=fps,
        row_names=row_names,
        individual=[key[1] for key in order] if has_ind else None,
    )
