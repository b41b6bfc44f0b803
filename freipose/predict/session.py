"""Recording sessions for prediction: discovery and validation before any work starts.

A *session* is a folder with one video per camera (camera name = file stem, matching the
calibration), or an explicit list of video files. Everything that can be checked cheaply is
checked here, so that a bad input fails in seconds rather than hours into a run: every
video opens and decodes its first frame, every camera is in the calibration, image sizes
match the calibration, and the frame rate is known. Videos of different lengths are cut to
the common length (with a warning).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType

import numpy as np

from freipose._frozen import PicklableFrozen
from freipose.geometry.camera import CameraRig
from freipose.io.calibration import load_calibration
from freipose.io.video import (
    VIDEO_SUFFIXES,
    FrameSource,
    MediaError,
    find_camera_videos,
    frame_range,
)

log = logging.getLogger(__name__)

CALIBRATION_NAMES = ("calibration.toml",)


class SessionError(ValueError):
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
        return self.rig.names


def _is_video(p: Path) -> bool:
    return p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES


def _find_calibration(folder: Path) -> Path | None:
    for name in CALIBRATION_NAMES:
        if (folder / name).is_file():
            return folder / name
    return None


def parse_frames(spec: str | None, num_frames: int) -> tuple[int, int]:
    """Frame range ``START:STOP`` clipped to the video as ``(start, stop)``; see
    :func:`freipose.io.video.frame_range`.

    Raises:
        ValueError: malformed spec or an empty range.
    """
    r = frame_range(spec, num_frames)
    return r.start, r.stop


def open_session(
    videos: Mapping[str, str | Path],
    rig: CameraRig,
    name: str,
    calibration_path: Path | None = None,
) -> Session:
    """Validate videos (camera -> path) against a rig and return the :class:`Session`.

    Raises:
        SessionError: a camera is missing from the calibration, an image size differs from
            the calibration, fewer than two cameras, or no frame rate.
        MediaError: a video cannot be opened or decoded.
    """
    where = f" ({calibration_path})" if calibration_path else ""
    vids = {str(c): Path(p) for c, p in videos.items()}
    unknown = [c for c in vids if c not in rig.names]
    if unknown:
        raise SessionError(
            f"session {name!r}: cameras {unknown} have videos but are not in the calibration"
            f"{where}, which has cameras {rig.names}. Rename the videos to the calibration's "
            f"camera names (camera name = video file stem) or pass the matching --calibration."
        )
    unused = [c for c in rig.names if c not in vids]
    if unused:
        log.warning(
            "session %r: calibrated cameras %s have no video; predicting from %s",
            name,
            unused,
            list(vids),
        )
    if len(vids) < 2:
        raise SessionError(
            f"session {name!r}: found videos for {list(vids)}; 3D prediction needs at least two "
            f"cameras of the calibration{where}"
        )
    lengths: dict[str, int] = {}
    fps_all: dict[str, float] = {}
    for cam, path in vids.items():
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
            fps_all[cam] = float(src.fps)
    n = min(lengths.values())
    if len(set(lengths.values())) > 1:
        log.warning(
            "session %r: videos have different lengths %s; using the common length %d",
            name,
            lengths,
            n,
        )
    if n <= 0:
        raise SessionError(f"session {name!r}: a video has no frames ({lengths})")
    fps_vals = [f for f in fps_all.values() if np.isfinite(f) and f > 0]
    if not fps_vals:
        raise SessionError(
            f"session {name!r}: no video states its frame rate; re-encode the videos with a "
            f"frame rate (e.g. ffmpeg -r 30 ...)"
        )
    if max(fps_vals) - min(fps_vals) > 1e-3 * max(fps_vals):
        log.warning(
            "session %r: videos have different frame rates %s; using %g", name, fps_all, fps_vals[0]
        )
    order = list(vids)
    return Session(
        name=name,
        videos={c: vids[c] for c in order},
        rig=rig.subset(order),
        num_frames=n,
        fps=fps_vals[0],
        lengths=lengths,
        calibration_path=calibration_path,
    )


def discover_sessions(
    inputs: Sequence[str | Path], calibration: str | Path | None = None
) -> list[Session]:
    """Sessions from command-line inputs: folders (one session each) or video files (one session).

    Args:
        inputs: session folders, or the video files of one session (camera = file stem; the
            session is named after the videos' folder).
        calibration: calibration file for all sessions; default ``calibration.toml`` in each
            session folder (in the videos' folder for a list of videos).

    Raises:
        SessionError, MediaError, FileNotFoundError: see :func:`open_session`; also mixed
            folders and files, duplicate session names, no calibration found.
    """
    paths = [Path(p) for p in inputs]
    if not paths:
        raise SessionError("no session given; pass session folders or the videos of one session")
    missing = [str(p) for p in paths if not p.exists()]
    if missing:
        raise FileNotFoundError(f"sessions not found: {missing}")
    dirs = [p for p in paths if p.is_dir()]
    files = [p for p in paths if not p.is_dir()]
    if dirs and files:
        raise SessionError(
            "give either session folders or the video files of one session, not both "
            f"(folders {[str(d) for d in dirs]}, files {[str(f) for f in files]})"
        )
    groups: list[tuple[str, dict[str, Path], Path]] = []
    if files:
        bad = [str(f) for f in files if not _is_video(f)]
        if bad:
            raise MediaError(f"not video files ({', '.join(VIDEO_SUFFIXES)}): {bad}")
        vids: dict[str, Path] = {}
        for f in files:
            if f.stem in vids:
                raise SessionError(f"two videos for camera {f.stem!r}: {vids[f.stem]} and {f}")
            vids[f.stem] = f
        folder = files[0].resolve().parent
        groups.append((folder.name, vids, folder))
    else:
        for d in dirs:
            groups.append((d.resolve().name, find_camera_videos(d), d))
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
        if fixed_rig is not None:
            rig, cpath = fixed_rig, Path(calibration)  # type: ignore[arg-type]
        else:
            cpath = _find_calibration(folder)
            if cpath is None:
                raise SessionError(
                    f"session {name!r}: no {CALIBRATION_NAMES[0]} in {folder}; "
                    "pass --calibration FILE"
                )
            rig = load_calibration(cpath)
        sessions.append(open_session(vids, rig, name, cpath))
    return sessions
