"""SLEAP ``.slp`` label files, read with sleap-io (``pip install 'freipose[sleap]'``).

A multi-camera file (with a recording session) gives one session: cameras from the
session's video-to-camera map, cross-view identity from its instance groups when present,
else from tracks. Otherwise each ``.slp`` is one camera (its name from ``--camera-map``, a
calibration camera in the file name, or the file stem). Only user-labeled instances are
imported (predictions are not labels). Videos are found by base name next to the file or
in a ``videos`` folder.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from freipose.geometry.camera import Camera, CameraRig
from freipose.labels.importing import LabelImportError, SourceLabels
from freipose.labels.mapping import NameMapping
from freipose.labels.views import (
    ViewTable,
    camera_from_name,
    combine_views,
    existing_path,
    match_camera,
)

log = logging.getLogger(__name__)

# (frame, individual, camera -> instance): one animal at one instant across the views
Group = tuple[int, str, dict[str, Any]]


def _sleap_rig(session: object) -> CameraRig | None:
    """The cameras of a SLEAP recording session, or None when a camera has no image size."""
    cg = getattr(session, "camera_group", None)
    cams = []
    for c in getattr(cg, "cameras", []) or []:
        if c.size is None:
            return None
        cams.append(
            Camera.from_rvec(
                str(c.name),
                tuple(int(x) for x in c.size),
                np.asarray(c.matrix, dtype=np.float64),
                np.asarray(c.dist, dtype=np.float64).ravel()[:5],
                np.asarray(c.rvec, dtype=np.float64),
                np.asarray(c.tvec, dtype=np.float64),
            )
        )
    return CameraRig(tuple(cams), {"source_format": "SLEAP session"}) if cams else None


def _resolve_video(filename: str, near: Path) -> Path | None:
    """A video by its base name next to ``near``, in ``near/videos`` or ``near/../videos``."""
    base = Path(str(filename).replace("\\", "/")).name
    for d in (near, near / "videos", near.parent / "videos"):
        if (d / base).is_file():
            return d / base
    return None


@dataclass(frozen=True, eq=False)
class SlpFile:
    """A loaded ``.slp`` file.

    Attributes:
        path: the file.
        labels: the sleap-io ``Labels``.
        keypoints: (K,) node names of its first skeleton.
        user: (labeled frame, instance) of every user-labeled instance.
    """

    path: Path
    labels: Any
    keypoints: list[str]
    user: list[tuple[Any, Any]]


def load_slp_file(sio: Any, src: Path) -> SlpFile:
    """Load one ``.slp`` file and its user-labeled instances.

    Args:
        sio: the ``sleap_io`` module.
        src: the file.

    Returns:
        The loaded file.

    Raises:
        InputFileError: no such file.
        LabelImportError: not readable, no skeleton, or no user-labeled instance.
    """
    path = existing_path(Path(src), "SLEAP file")
    try:
        labels = sio.load_slp(str(path))
    except Exception as exc:  # sleap-io raises many kinds for bad files
        raise LabelImportError(f"{path}: not a readable SLEAP .slp file ({exc})") from exc
    if not labels.skeletons:
        raise LabelImportError(f"{path}: the file has no skeleton")
    kps = list(labels.skeletons[0].node_names)
    user = [
        (lf, inst)
        for lf in labels.labeled_frames
        for inst in lf.instances
        if type(inst).__name__ == "Instance"
    ]
    if not user:
        raise LabelImportError(
            f"{path}: no user-labeled instances (only predictions); label frames in SLEAP "
            f"or promote predictions to user instances first"
        )
    return SlpFile(path, labels, kps, user)


def _session_cameras(slp: SlpFile, rs: Any) -> dict[int, str]:
    """Camera name of every video of the session (keyed by ``id(video)``)."""
    cam_of = {}
    for vid in slp.labels.videos:
        cam = rs.get_camera(vid)
        if cam is None:
            continue
        cam_of[id(vid)] = str(cam.name)
        stem = Path(str(vid.filename).replace("\\", "/")).stem
        if match_camera(stem, [cam.name]) is None:
            log.warning("%s: video %s is mapped to camera %s", slp.path, stem, cam.name)
    return cam_of


def _session_groups(slp: SlpFile, rs: Any, cam_of: dict[int, str]) -> list[Group]:
    """Cross-view groups: the session's instance groups, else user instances by track.

    Args:
        slp: the loaded file.
        rs: its recording session.
        cam_of: camera of every video (keyed by ``id(video)``).

    Returns:
        (frame, individual, camera -> instance) sorted by frame and individual.

    Raises:
        LabelImportError: a camera has several instances of one track in a frame.
    """
    groups: list[Group] = []
    fgs = getattr(rs, "frame_groups", {}) or {}
    for fidx, fg in sorted(fgs.items()):
        for g, ig in enumerate(fg.instance_groups):
            by_cam = {str(c.name): inst for c, inst in ig.instance_by_camera.items()}
            groups.append((int(fidx), f"group{g}", by_cam))
    if groups:
        return groups
    tmp: dict[tuple[int, str], dict[str, object]] = {}
    for lf, inst in slp.user:
        cam = cam_of.get(id(lf.video))
        if cam is None:
            continue
        tr = inst.track.name if inst.track is not None else ""
        d = tmp.setdefault((int(lf.frame_idx), tr), {})
        if cam in d:
            raise LabelImportError(
                f"{slp.path}: frame {lf.frame_idx} of camera {cam} has several "
                f"instances of track {tr!r}; cross-view identity is ambiguous"
            )
        d[cam] = inst
    return [(f, tr, d) for (f, tr), d in sorted(tmp.items())]


def read_session_file(
    slp: SlpFile, rs: Any, calibration: CameraRig | None, session: str | None
) -> SourceLabels:
    """The labels of a multi-camera ``.slp`` file (one with a recording session).

    Args:
        slp: the loaded file.
        rs: its (first) recording session.
        calibration: cameras for the session (default: the session's own).
        session: the session name (default: the file stem).

    Returns:
        The session's labels.
    """
    rig = calibration or _sleap_rig(rs)
    cam_of = _session_cameras(slp, rs)
    groups = _session_groups(slp, rs, cam_of)
    # calibration order; cameras the calibration lacks follow in the file's video order
    cams = sorted(
        dict.fromkeys(cam_of.values()),
        key=lambda c: list(rig.names).index(c) if rig and c in rig.names else 1e9,
    )
    kps = slp.keypoints
    vts = []
    for cam in cams:
        rows = [(f, ind, d[cam]) for f, ind, d in groups if cam in d]
        vts.append(
            ViewTable(
                str(slp.path),
                cam,
                kps,
                np.array([r[0] for r in rows], dtype=np.int64),
                np.array([np.asarray(r[2].numpy(), dtype=np.float64) for r in rows]).reshape(
                    len(rows), len(kps), 2
                ),
                [f"frame {r[0]} {r[1]}" for r in rows],
                [r[1] for r in rows],
            )
        )
    videos = {}
    for vid in slp.labels.videos:
        if id(vid) in cam_of:
            p = _resolve_video(vid.filename, slp.path.parent)
            if p is not None:
                videos[cam_of[id(vid)]] = p
    return combine_views(session or slp.path.stem, vts, rig, videos)


@dataclass(frozen=True, eq=False)
class SingleView:
    """The labels of a one-camera ``.slp`` file.

    Attributes:
        session: the session it belongs to.
        table: its camera's labels.
        video: the labeled video, if found.
    """

    session: str
    table: ViewTable
    video: Path | None


def read_single_view(
    slp: SlpFile, calibration: CameraRig | None, mapping: NameMapping, session: str | None
) -> SingleView:
    """The labels of a ``.slp`` file of one camera.

    Args:
        slp: the loaded file.
        calibration: the cameras; a calibration camera must be named in the file name.
        mapping: ``--camera-map`` renames.
        session: the session name (default: from the file name, else ``session``).

    Returns:
        The camera's labels and video.

    Raises:
        LabelImportError: the file has several videos, or names no calibration camera.
    """
    path = slp.path
    cam, sess = camera_from_name(path.stem, path, calibration, mapping)
    if len(slp.labels.videos) > 1:
        raise LabelImportError(
            f"{path}: {len(slp.labels.videos)} videos but no recording session linking them "
            f"to cameras; use one .slp per camera or a SLEAP multi-view session"
        )
    rows = sorted(
        ((int(lf.frame_idx), inst.track.name if inst.track else "", inst) for lf, inst in slp.user),
        key=lambda r: (r[0], r[1]),
    )
    table = ViewTable(
        str(path),
        cam,
        slp.keypoints,
        np.array([r[0] for r in rows], dtype=np.int64),
        np.array([np.asarray(r[2].numpy(), dtype=np.float64) for r in rows]),
        [f"frame {r[0]} {r[1]}".strip() for r in rows],
        [r[1] for r in rows] if any(r[1] for r in rows) else None,
    )
    video = _resolve_video(slp.labels.videos[0].filename, path.parent)
    return SingleView(session or sess or "session", table, video)


def read_sleap(
    sources: Sequence[Path],
    calibration: CameraRig | None,
    mapping: NameMapping,
    session: str | None = None,
) -> list[SourceLabels]:
    """SLEAP ``.slp`` files (see the module docstring).

    Args:
        sources: the ``.slp`` files.
        calibration: cameras for every session (default: a multi-view file's own).
        mapping: ``--camera-map`` renames.
        session: the session name of every file.

    Returns:
        One source per multi-camera file, then one per session of one-camera files.

    Raises:
        LabelImportError: sleap-io is missing, or a file cannot be imported.
    """
    try:
        import sleap_io as sio
    except ImportError as exc:
        raise LabelImportError(
            "reading SLEAP files needs sleap-io: pip install 'freipose[sleap]'"
        ) from exc
    single: dict[str, list[ViewTable]] = {}
    single_videos: dict[str, dict[str, Path]] = {}
    out = []
    for src in sources:
        slp = load_slp_file(sio, src)
        sessions = list(getattr(slp.labels, "sessions", []) or [])
        if sessions:
            out.append(read_session_file(slp, sessions[0], calibration, session))
            continue
        view = read_single_view(slp, calibration, mapping, session)
        single.setdefault(view.session, []).append(view.table)
        if view.video is not None:
            single_videos.setdefault(view.session, {})[view.table.camera] = view.video
    for sname, vts in single.items():
        out.append(combine_views(sname, vts, calibration, single_videos.get(sname, {})))
    return out
