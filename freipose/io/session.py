"""Recording sessions: discovery and validation before any work starts.

A *session* is a folder with one video per camera, ``<camera>.<ext>`` (camera name = file
stem, matching the calibration) or ``<camera>/<any name>.<ext>`` (sleap-anipose's layout;
see :func:`~freipose.io.video.find_camera_videos`), or an explicit list of video files.
Everything that can be checked cheaply is checked here, so that a bad input fails in
seconds rather than hours into a run: every video opens and decodes its first frame, the
cameras are in the calibration, image sizes match the calibration, and (where asked) the
frame rate is known. Videos of different lengths are cut to the common length (with a
warning).

Prediction (``freipose predict``) takes every video as a camera (``cameras="videos"``);
detection (``freipose detect``) takes the calibrated cameras that have a video, in the
calibration's order (``cameras="calibration"``), and needs no frame rate.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Literal

import numpy as np

from freipose._frozen import PicklableFrozen
from freipose.errors import FreiPoseError, InputFileError
from freipose.geometry.camera import CameraRig
from freipose.io.calibration import load_calibration
from freipose.io.video import VIDEO_SUFFIXES, FrameSource, MediaError, find_camera_videos

log = logging.getLogger(__name__)

TRUE_CALIBRATION_NAME = "true_calibration.toml"  # a synthetic session's true rig (freipose synth)
CALIBRATION_NAMES = ("calibration.toml", TRUE_CALIBRATION_NAME)  # looked for in this order

Cameras = Literal["videos", "calibration"]


class SessionError(FreiPoseError):
    """A session cannot be predicted as given; the message says why and how to fix it."""


@dataclass(frozen=True, eq=False)
class Session(PicklableFrozen):
    """One synchronized multi-camera recording, validated.

    Attributes:
        name: output stem (``<name>.poses.h5``).
        videos: camera name -> video path, in the order of ``rig``.
        rig: the calibrated cameras that have a video (C), in video order.
        num_frames: common number of frames over the cameras.
        fps: frame rate of the videos.
        lengths: camera name -> number of frames its container announces.
        calibration_path: the calibration file used.
    """

    name: str
    videos: Mapping[str, Path]
    rig: CameraRig
    num_frames: int
    fps: float
    lengths: Mapping[str, int] = field(default_factory=dict)
    calibration_path: Path | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "videos", MappingProxyType(dict(self.videos)))
        object.__setattr__(self, "lengths", MappingProxyType(dict(self.lengths)))
        if list(self.videos) != self.rig.names:
            raise ValueError(
                f"session {self.name!r}: videos {list(self.videos)} and rig cameras "
                f"{self.rig.names} must be in the same order"
            )

    @property
    def cameras(self) -> list[str]:
        """The camera names, in video order."""
        return self.rig.names


def _is_video(p: Path) -> bool:
    return p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES


def _find_calibration(folder: Path) -> Path | None:
    for name in CALIBRATION_NAMES:
        if (folder / name).is_file():
            return folder / name
    return None


def _session_cameras(
    vids: Mapping[str, Path], rig: CameraRig, name: str, where: str, cameras: Cameras
) -> list[str]:
    """The cameras of a session: every video's (in video order) or the calibration's.

    Raises:
        SessionError: with ``cameras="videos"``, a video of a camera that is not in the
            calibration; fewer than two cameras.
    """
    if cameras == "videos":
        unknown = [c for c in vids if c not in rig.names]
        if unknown:
            raise SessionError(
                f"session {name!r}: cameras {unknown} have videos but are not in the "
                f"calibration{where}, which has cameras {rig.names}. Rename the videos to the "
                f"calibration's camera names (camera name = video file stem), map them "
                f"with --camera-map VIDEO_STEM=CAMERA, or pass the matching --calibration."
            )
        order = list(vids)
    else:
        order = [c for c in rig.names if c in vids]
    unused = [c for c in rig.names if c not in vids]
    if unused:
        log.warning(
            "session %r: calibrated cameras %s have no video; using %s", name, unused, order
        )
    if len(order) < 2:
        raise SessionError(
            f"session {name!r}: found videos for {list(vids)}, which match {order} of the "
            f"calibrated cameras {rig.names}{where}; 3D needs at least two cameras of the "
            f"calibration (camera name = video file stem, or map them with --camera-map "
            f"VIDEO_STEM=CAMERA)"
        )
    return order


@dataclass(frozen=True)
class _VideoFacts:
    """What the videos of a session announce.

    Attributes:
        lengths: camera -> number of frames.
        fps: camera -> frame rate (NaN or 0 where unknown).
    """

    lengths: dict[str, int]
    fps: dict[str, float]


def _probe_videos(
    vids: Mapping[str, Path], rig: CameraRig, order: Sequence[str], name: str, where: str
) -> _VideoFacts:
    """Open every camera's video, check its image size against the calibration.

    Raises:
        MediaError: a video cannot be opened or decoded.
        SessionError: an image size differs from the calibration.
    """
    lengths: dict[str, int] = {}
    fps: dict[str, float] = {}
    for cam in order:
        path = vids[cam]
        try:
            src = FrameSource(path)
        except MediaError as exc:
            raise MediaError(f"session {name!r}, camera {cam!r}: {exc}") from exc
        with src:
            want = tuple(int(v) for v in rig[cam].size)
            if tuple(src.size) != want:
                raise SessionError(
                    f"session {name!r}: video {path} is {src.size[0]}x{src.size[1]} but camera "
                    f"{cam!r} in the calibration{where} is {want[0]}x{want[1]}; use the videos the "
                    f"calibration was made for (or recalibrate at this resolution)"
                )
            lengths[cam] = int(src.num_frames)
            fps[cam] = float(src.fps)
    return _VideoFacts(lengths, fps)


def _common_fps(facts: _VideoFacts, name: str, need_fps: bool) -> float:
    """The session's frame rate: the first camera's known one (NaN if none and not needed).

    Raises:
        SessionError: ``need_fps`` and no video states its frame rate.
    """
    vals = [f for f in facts.fps.values() if np.isfinite(f) and f > 0]
    if not vals:
        if not need_fps:
            return float("nan")
        raise SessionError(
            f"session {name!r}: no video states its frame rate; re-encode the videos with a "
            f"frame rate (e.g. ffmpeg -r 30 ...)"
        )
    if max(vals) - min(vals) > 1e-3 * max(vals):
        log.warning(
            "session %r: videos have different frame rates %s; using %g", name, facts.fps, vals[0]
        )
    return vals[0]


def open_session(
    videos: Mapping[str, str | Path],
    rig: CameraRig,
    name: str,
    calibration_path: Path | None = None,
    *,
    cameras: Cameras = "videos",
    need_fps: bool = True,
) -> Session:
    """Validate videos (camera -> path) against a rig and return the :class:`Session`.

    Args:
        videos: camera name -> video file.
        rig: the calibration.
        name: the session name.
        calibration_path: the calibration file, for messages.
        cameras: ``"videos"``: every video is a camera, in the videos' order, and a video of
            a camera that is not calibrated is an error; ``"calibration"``: the calibrated
            cameras that have a video, in the calibration's order (other videos are
            ignored).
        need_fps: a session whose videos state no frame rate is an error (else its
            ``fps`` is NaN).

    Returns:
        The validated session.

    Raises:
        SessionError: a camera is missing from the calibration, an image size differs from
            the calibration, fewer than two cameras, or no frame rate.
        MediaError: a video cannot be opened or decoded.
    """
    where = f" ({calibration_path})" if calibration_path else ""
    vids = {str(c): Path(p) for c, p in videos.items()}
    order = _session_cameras(vids, rig, name, where, cameras)
    facts = _probe_videos(vids, rig, order, name, where)
    n = min(facts.lengths.values())
    if len(set(facts.lengths.values())) > 1:
        log.warning(
            "session %r: videos have different lengths %s; using the common length %d",
            name,
            facts.lengths,
            n,
        )
    if n <= 0:
        raise SessionError(f"session {name!r}: a video has no frames ({facts.lengths})")
    return Session(
        name=name,
        videos={c: vids[c] for c in order},
        rig=rig.subset(order),
        num_frames=n,
        fps=_common_fps(facts, name, need_fps),
        lengths=facts.lengths,
        calibration_path=calibration_path,
    )


def _input_groups(paths: Sequence[Path]) -> list[tuple[str, dict[str, Path] | None, Path]]:
    """``(session name, camera -> video, folder)`` per session of the command-line inputs.

    The videos of a session folder are ``None`` (listed once its calibration is found).

    Raises:
        SessionError, MediaError, InputFileError: see :func:`discover_sessions`.
    """
    if not paths:
        raise SessionError("no session given; pass session folders or the videos of one session")
    missing = [str(p) for p in paths if not p.exists()]
    if missing:
        raise InputFileError(f"sessions not found: {missing}")
    dirs = [p for p in paths if p.is_dir()]
    files = [p for p in paths if not p.is_dir()]
    if dirs and files:
        raise SessionError(
            "give either session folders or the video files of one session, not both "
            f"(folders {[str(d) for d in dirs]}, files {[str(f) for f in files]})"
        )
    if not files:
        return [(d.resolve().name, None, d) for d in dirs]
    bad = [str(f) for f in files if not _is_video(f)]
    if bad:
        raise MediaError(f"not video files ({', '.join(VIDEO_SUFFIXES)}): {bad}")
    vids: dict[str, Path] = {}
    for f in files:
        if f.stem in vids:
            raise SessionError(f"two videos for camera {f.stem!r}: {vids[f.stem]} and {f}")
        vids[f.stem] = f
    folder = files[0].resolve().parent
    found: dict[str, Path] | None = vids
    return [(folder.name, found, folder)]


def _renamed_videos(
    vids: Mapping[str, Path], camera_map: Mapping[str, str], name: str
) -> dict[str, Path]:
    """``vids`` (stem -> video) with the stems ``camera_map`` names renamed to cameras.

    Raises:
        SessionError: a mapped stem is not a video of the session, or two videos get
            one camera name.
    """
    unknown = [old for old in camera_map if old not in vids]
    if unknown:
        raise SessionError(
            f"session {name!r}: --camera-map names {unknown}, which are not video file stems "
            f"of the session (its videos: {list(vids)}); write --camera-map VIDEO_STEM=CAMERA"
        )
    out: dict[str, Path] = {}
    for stem, path in vids.items():
        cam = camera_map.get(stem, stem)
        if cam in out:
            raise SessionError(
                f"session {name!r}: two videos for camera {cam!r} after --camera-map: "
                f"{out[cam]} and {path}"
            )
        out[cam] = path
    return out


def discover_sessions(
    inputs: Sequence[str | Path],
    calibration: str | Path | None = None,
    *,
    cameras: Cameras = "videos",
    need_fps: bool = True,
    camera_map: Mapping[str, str] | None = None,
) -> list[Session]:
    """Sessions from command-line inputs: folders (one session each) or video files (one session).

    Args:
        inputs: session folders, or the video files of one session (camera = file stem; the
            session is named after the videos' folder).
        calibration: calibration file for all sessions; default ``calibration.toml`` in each
            session folder (in the videos' folder for a list of videos).
        cameras: which cameras a session has; see :func:`open_session`.
        need_fps: the videos must state their frame rate; see :func:`open_session`.
        camera_map: video file stem -> camera name, for videos not named after their
            cameras (e.g. ``min_session_back`` -> ``back``); other stems stay as they are.

    Returns:
        One validated session per folder (or one for the video files).

    Raises:
        SessionError, MediaError: see :func:`open_session`; also mixed folders and files,
            duplicate session names, a ``camera_map`` entry that names no video of a
            session or maps two videos to one camera.
        InputFileError: an input does not exist, or no calibration is found.
    """
    groups = _input_groups([Path(p) for p in inputs])
    names = [g[0] for g in groups]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise SessionError(
            f"several sessions are named {dup} (the folder name names the output file); "
            f"rename the folders or predict them into different output folders"
        )
    fixed_rig = load_calibration(calibration) if calibration is not None else None
    sessions = []
    for name, vids, folder in groups:
        if fixed_rig is not None and calibration is not None:
            rig, cpath = fixed_rig, Path(calibration)
        else:
            found = _find_calibration(folder)
            if found is None:
                raise InputFileError(
                    f"session {name!r}: calibration not found: no {CALIBRATION_NAMES[0]} in "
                    f"{folder}; pass --calibration FILE or put {CALIBRATION_NAMES[0]} in the "
                    f"session folder"
                )
            rig, cpath = load_calibration(found), found
        if vids is None:
            vids = find_camera_videos(folder)
        if camera_map:
            vids = _renamed_videos(vids, camera_map, name)
        sessions.append(open_session(vids, rig, name, cpath, cameras=cameras, need_fps=need_fps))
    return sessions
