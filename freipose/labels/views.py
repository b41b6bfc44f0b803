"""Per-camera label tables of the format readers.

Frames and cameras from file and folder names, and the join of one session's per-camera
tables into :class:`~freipose.labels.importing.SourceLabels`.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from freipose.errors import InputFileError
from freipose.geometry.camera import CameraRig
from freipose.labels.importing import LabelImportError, SourceLabels
from freipose.labels.mapping import NameMapping


def existing_path(path: str | Path, what: str) -> Path:
    """``path`` as a Path, checked to exist.

    Args:
        path: the file or folder a user named.
        what: what it is ("SLEAP file"), for messages.

    Returns:
        The path.

    Raises:
        InputFileError: it does not exist.
    """
    p = Path(path)
    if not p.exists():
        raise InputFileError(f"{what} not found: {p}")
    return p


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
