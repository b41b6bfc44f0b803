"""SLEAP ``.slp`` label files, read with sleap-io (``pip install 'freipose[sleap]'``).

A multi-camera file (with a recording session) gives one session: cameras from the
session's video-to-camera map, cross-view identity from its instance groups when present
(each group one animal at one instant, named by the group's identity, else by the track its
instances share; :func:`group_identity`), else from tracks. The animal's name becomes the
row's ``individual`` in ``labels.h5``. Otherwise each ``.slp`` is one camera: its name from
``--camera-map``, a calibration camera in the file name, or the file stem; a folder
``session/<camera>/*.slp`` (sleap-anipose's layout) gives one session named after the
folder, a camera per subfolder, and the folder's ``calibration.toml`` when no calibration
is given.

Which instances are imported is a choice (``instances``): ``user`` (hand-labeled, the
default), ``predicted`` (SLEAP's predictions, e.g. proofread ones as sleap-anipose's
workflow leaves them) or ``all`` (user instances, and predictions where a frame has no
user instance of that track). Of several predictions of one track in a frame the one with
the highest score is kept. Videos are found as stored in the file, else by base name next
to the file or in a ``videos`` folder.
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
    """A video as stored in the file (absolute, or relative to ``near``), else by base name.

    The path is kept as found (a symlinked video keeps its link's path).
    """
    stored = Path(str(filename).replace("\\", "/"))
    for cand in (stored, near / stored) if str(filename) else ():
        if cand.is_file():
            return cand
    base = stored.name
    for d in (near, near / "videos", near.parent / "videos"):
        if base and (d / base).is_file():
            return d / base
    return None


INSTANCE_KINDS = ("user", "predicted", "all")


def _is_predicted(inst: Any) -> bool:
    """Whether a sleap-io instance is a prediction (``PredictedInstance``)."""
    return type(inst).__name__ == "PredictedInstance"


def _track(inst: Any) -> str:
    return inst.track.name if inst.track is not None else ""


def select_instances(labeled_frames: Sequence[Any], kind: str) -> list[tuple[Any, Any]]:
    """The (labeled frame, instance) pairs to import (see the module docstring).

    Args:
        labeled_frames: sleap-io ``LabeledFrame`` s.
        kind: ``user``, ``predicted`` or ``all``.

    Returns:
        The chosen pairs in file order: user instances as they are; of the predictions of
        one track in one frame the highest-scoring one (with ``all`` only where the frame
        has no user instance of that track).
    """
    out = []
    for lf in labeled_frames:
        user = [i for i in lf.instances if not _is_predicted(i)]
        best: dict[str, Any] = {}
        if kind != "user":
            taken = {_track(i) for i in user} if kind == "all" else set()
            for i in lf.instances:
                tr = _track(i)
                if not _is_predicted(i) or tr in taken:
                    continue
                if tr not in best or float(i.score or 0) > float(best[tr].score or 0):
                    best[tr] = i
        chosen = ([] if kind == "predicted" else user) + list(best.values())
        out += [(lf, i) for i in chosen]
    return out


@dataclass(frozen=True, eq=False)
class SlpFile:
    """A loaded ``.slp`` file.

    Attributes:
        path: the file.
        labels: the sleap-io ``Labels``.
        keypoints: (K,) node names of its first skeleton.
        chosen: (labeled frame, instance) of every instance to import.
        kind: which instances were chosen (``user``, ``predicted``, ``all``).
    """

    path: Path
    labels: Any
    keypoints: list[str]
    chosen: list[tuple[Any, Any]]
    kind: str = "user"


def load_slp_file(sio: Any, src: Path, kind: str = "user") -> SlpFile:
    """Load one ``.slp`` file and the instances of ``kind``.

    Args:
        sio: the ``sleap_io`` module.
        src: the file.
        kind: ``user``, ``predicted`` or ``all`` (see :func:`select_instances`).

    Returns:
        The loaded file.

    Raises:
        InputFileError: no such file.
        LabelImportError: not readable, no skeleton, or no instance of ``kind``.
    """
    if kind not in INSTANCE_KINDS:
        raise LabelImportError(f"--instances must be one of {list(INSTANCE_KINDS)}, got {kind!r}")
    path = existing_path(Path(src), "SLEAP file")
    try:
        labels = sio.load_slp(str(path))
    except Exception as exc:  # sleap-io raises many kinds for bad files
        raise LabelImportError(f"{path}: not a readable SLEAP .slp file ({exc})") from exc
    if not labels.skeletons:
        raise LabelImportError(f"{path}: the file has no skeleton")
    kps = list(labels.skeletons[0].node_names)
    chosen = select_instances(labels.labeled_frames, kind)
    if not chosen:
        n_pred = sum(_is_predicted(i) for lf in labels.labeled_frames for i in lf.instances)
        n_all = sum(len(lf.instances) for lf in labels.labeled_frames)
        raise LabelImportError(
            f"{path}: no {kind} instances (the file holds {n_all - n_pred} user-labeled and "
            f"{n_pred} predicted ones); pass --instances predicted to import predictions "
            f"(e.g. proofread ones), --instances all for both, or label frames in SLEAP"
        )
    return SlpFile(path, labels, kps, chosen, kind)


def group_identity(group: Any, index: int, path: Path, frame: int) -> str:
    """The animal of a SLEAP instance group: its identity, else its instances' track.

    Args:
        group: a sleap-io ``InstanceGroup``.
        index: its position in its frame group.
        path: the file (for messages).
        frame: its frame (for messages).

    Returns:
        The identity's name, else the one track all its instances share, else the group's
        name (``instance_group_<index>``; such names do not link the animal across frames).

    Raises:
        LabelImportError: the group's instances belong to different tracks.
    """
    ident = getattr(group, "identity", None)
    if ident is not None and getattr(ident, "name", ""):
        return str(ident.name)
    tracks = {_track(i) for i in group.instance_by_camera.values()}
    tracks.discard("")
    if len(tracks) > 1:
        raise LabelImportError(
            f"{path}: instance group {index} of frame {frame} joins instances of the tracks "
            f"{sorted(tracks)}; one group is one animal: fix the tracks or the group in SLEAP"
        )
    if tracks:
        return tracks.pop()
    name = dict(getattr(group, "metadata", {}) or {}).get("name") or f"instance_group_{index}"
    return str(name)


def _named(group: Any) -> bool:
    """Whether an instance group names its animal (an identity, or a track of an instance)."""
    ident = getattr(group, "identity", None)
    if ident is not None and getattr(ident, "name", ""):
        return True
    return any(_track(i) for i in group.instance_by_camera.values())


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
    unnamed: list[int] = []  # frames with a group that names no animal
    fgs = getattr(rs, "frame_groups", {}) or {}
    for fidx, fg in sorted(fgs.items()):
        for g, ig in enumerate(fg.instance_groups):
            by_cam = {
                str(c.name): inst
                for c, inst in ig.instance_by_camera.items()
                if slp.kind == "all" or (slp.kind == "predicted") == _is_predicted(inst)
            }
            if not by_cam:
                continue
            groups.append((int(fidx), group_identity(ig, g, slp.path, int(fidx)), by_cam))
            if not _named(ig):
                unnamed.append(int(fidx))
    if unnamed and len(unnamed) == len(groups) == len({f for f, _, _ in groups}):
        return [(f, "", d) for f, _, d in groups]  # one unnamed animal per frame: one animal
    if unnamed:
        log.warning(
            "%s: %d instance groups (first in frame %d) have neither an identity nor a track; "
            "their animals are named after the groups, which does not link them across frames",
            slp.path, len(unnamed), unnamed[0],
        )  # fmt: skip
    if groups:
        seen: dict[tuple[int, str], int] = {}
        for f, ind, _ in groups:
            seen[(f, ind)] = seen.get((f, ind), 0) + 1
        twice = sorted(k for k, n in seen.items() if n > 1)
        if twice:
            f, ind = twice[0]
            raise LabelImportError(
                f"{slp.path}: frame {f} has {seen[twice[0]]} instance groups of the animal "
                f"{ind!r}; give each group its own identity or track in SLEAP"
            )
        return sorted(groups, key=lambda r: (r[0], r[1]))
    tmp: dict[tuple[int, str], dict[str, object]] = {}
    for lf, inst in slp.chosen:
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
                [f"frame {r[0]} {r[1]}".strip() for r in rows],
                [r[1] for r in rows] if any(r[1] for r in rows) else None,
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
    slp: SlpFile,
    calibration: CameraRig | None,
    mapping: NameMapping,
    session: str | None,
    where: SlpSource | None = None,
) -> SingleView:
    """The labels of a ``.slp`` file of one camera.

    Args:
        slp: the loaded file.
        calibration: the cameras; a calibration camera must be named in the file name
            (or in the name of its camera folder).
        mapping: ``--camera-map`` renames.
        session: the session name (default: from the file or folder name, else ``session``).
        where: the camera and session names the file's place gives (default: the file stem).

    Returns:
        The camera's labels and video.

    Raises:
        LabelImportError: the file has several videos, or names no calibration camera.
    """
    path = slp.path
    name, kind = (where.camera, "folder") if where and where.camera else (path.stem, "file")
    cam, sess = camera_from_name(name, path, calibration, mapping, kind)
    if where is not None and where.session:
        sess = where.session
    if len(slp.labels.videos) > 1:
        raise LabelImportError(
            f"{path}: {len(slp.labels.videos)} videos but no recording session linking them "
            f"to cameras; use one .slp per camera or a SLEAP multi-view session"
        )
    rows = sorted(
        ((int(lf.frame_idx), _track(inst), inst) for lf, inst in slp.chosen),
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


@dataclass(frozen=True)
class SlpSource:
    """A ``.slp`` file to read and what its place says.

    Attributes:
        path: the file.
        camera: the camera folder's name (sleap-anipose layout), or "" (the file stem).
        session: the session folder's name, or "".
        calibration: ``calibration.toml`` of the session folder, when there is one.
    """

    path: Path
    camera: str = ""
    session: str = ""
    calibration: Path | None = None


def expand_sources(sources: Sequence[Path], calibration: CameraRig | None) -> list[SlpSource]:
    """The ``.slp`` files of the arguments (files, or session folders).

    A folder holding ``.slp`` files gives each of them; a folder whose subfolders hold them
    (``session/<camera>/*.slp``) gives one per subfolder, the camera named after it. A file
    whose stem names no calibration camera but whose folder does takes the folder's name.

    Args:
        sources: files and folders.
        calibration: the calibration (to tell camera names in file names).

    Returns:
        The files to read.

    Raises:
        LabelImportError: a folder without ``.slp`` files, or a camera folder with several.
    """
    out = []
    for src in map(Path, sources):
        if not src.is_dir():
            stem_cam = calibration is not None and match_camera(src.stem, calibration.names)
            in_cam_dir = calibration is not None and src.parent.name in calibration.names
            if calibration is not None and not stem_cam and in_cam_dir:
                out.append(SlpSource(src, src.parent.name, src.parent.parent.name))
            else:
                out.append(SlpSource(src))
            continue
        direct = sorted(src.glob("*.slp"))
        cal = src / "calibration.toml"
        cal_path = cal if cal.is_file() else None
        if direct:
            out += [SlpSource(f, "", "", cal_path) for f in direct]
            continue
        subs = [d for d in sorted(src.iterdir()) if d.is_dir() and any(d.glob("*.slp"))]
        if not subs:
            raise LabelImportError(
                f"{src}: no .slp files in the folder or its subfolders (expected "
                f"session/<camera>/*.slp, one file per camera)"
            )
        for d in subs:
            files = sorted(d.glob("*.slp"))
            if len(files) > 1:
                raise LabelImportError(
                    f"{d}: {len(files)} .slp files ({[f.name for f in files]}) for camera "
                    f"{d.name!r}; keep one per camera folder or pass the files themselves"
                )
            out.append(SlpSource(files[0], d.name, src.name, cal_path))
    return out


def _folder_rig(items: Sequence[SlpSource]) -> CameraRig | None:
    """The session folder's own ``calibration.toml`` (the first one found), or None."""
    from freipose.io.calibration import load_calibration

    for it in items:
        if it.calibration is not None:
            return load_calibration(it.calibration)
    return None


def read_sleap(
    sources: Sequence[Path],
    calibration: CameraRig | None,
    mapping: NameMapping,
    session: str | None = None,
    instances: str = "user",
) -> list[SourceLabels]:
    """SLEAP ``.slp`` files and session folders (see the module docstring).

    Args:
        sources: the ``.slp`` files, or session folders (``session/<camera>/*.slp``).
        calibration: cameras for every session (default: a multi-view file's own, or the
            session folder's ``calibration.toml``).
        mapping: ``--camera-map`` renames.
        session: the session name of every file.
        instances: ``user``, ``predicted`` or ``all`` (recorded in every source).

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
    items = expand_sources(sources, calibration)
    rig = calibration if calibration is not None else _folder_rig(items)
    single: dict[str, list[ViewTable]] = {}
    single_videos: dict[str, dict[str, Path]] = {}
    out = []
    for it in items:
        slp = load_slp_file(sio, it.path, instances)
        sessions = list(getattr(slp.labels, "sessions", []) or [])
        if sessions:
            out.append(read_session_file(slp, sessions[0], calibration, session))
            continue
        view = read_single_view(slp, rig, mapping, session, it)
        single.setdefault(view.session, []).append(view.table)
        if view.video is not None:
            single_videos.setdefault(view.session, {})[view.table.camera] = view.video
    for sname, vts in single.items():
        out.append(combine_views(sname, vts, rig, single_videos.get(sname, {})))
    for src in out:
        src.instances = instances
    return out
