"""Everything ``freipose label`` checks before the server starts, and the store it opens.

Bad input fails here with one clear message (a :class:`~freipose.errors.FreiPoseError`):
a session camera missing from the calibration, an unreadable video, a skeleton that does
not match an existing labels file or the predictions, a frame list naming other sessions
or frames outside the videos.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from freipose.errors import FreiPoseError
from freipose.io.labels import read_labels_h5
from freipose.io.poses import PoseData, read_poses_h5
from freipose.io.session import Session, discover_sessions
from freipose.labels.select import read_selection_csv
from freipose.labelui.store import Instant, LabelStore, StoreSettings, read_status
from freipose.skeleton import Skeleton, load_skeleton

log = logging.getLogger(__name__)


class LabelStartError(FreiPoseError):
    """The labeling tool cannot start with these inputs; the message says how to fix it."""


def _predictions(
    sessions: Sequence[Session], poses_dir: Path | None, skeleton: Skeleton
) -> dict[str, PoseData]:
    """``<poses_dir>/<session>.poses.h5`` per session that has one."""
    out: dict[str, PoseData] = {}
    if poses_dir is None:
        return out
    for s in sessions:
        path = poses_dir / f"{s.name}.poses.h5"
        if not path.is_file():
            log.warning("no predictions for session %r (%s not found)", s.name, path)
            continue
        data = read_poses_h5(path, require_up=False)
        if tuple(data.keypoints) != skeleton.keypoints:
            raise LabelStartError(
                f"{path}: its keypoints {list(data.keypoints)} differ from the skeleton "
                f"{skeleton.name!r} {list(skeleton.keypoints)}; pass the --skeleton the "
                f"predictions were made with, or another --poses-dir"
            )
        out[s.name] = data
    return out


def _confidence(pred: PoseData | None, frame: int) -> float:
    if pred is None:
        return float("nan")
    hit = np.flatnonzero(pred.frame_index == frame)
    if not len(hit):
        return float("nan")
    c = pred.confidence[hit[0]]
    return float(np.nanmean(c)) if np.isfinite(c).any() else 0.0


def choose_instants(
    sessions: Sequence[Session],
    frames: Path | None,
    per_session: int,
    predictions: dict[str, PoseData],
) -> list[Instant]:
    """The instants to label: the rows of ``frames`` (a selection CSV) or evenly spread.

    Args:
        sessions: the sessions.
        frames: a CSV of ``freipose labels select`` (session, frame_index, ...), kept in
            its order (least confident first), or None.
        per_session: with no CSV, this many instants spread evenly over each session.
        predictions: session -> predicted poses (for the instants' confidence).

    Raises:
        LabelStartError: the CSV names a session not given or a frame outside its videos;
            ``per_session < 1``.
    """
    by_name = {s.name: s for s in sessions}
    if frames is not None:
        rows = read_selection_csv(frames)
        unknown = sorted({name for name, _ in rows if name not in by_name})
        if unknown:
            raise LabelStartError(
                f"{frames}: sessions {unknown} are not among the sessions given "
                f"({sorted(by_name)}); pass their folders too or another --frames file"
            )
        bad = [(n, i) for n, i in rows if not 0 <= i < by_name[n].num_frames]
        if bad:
            raise LabelStartError(
                f"{frames}: frames {bad[:5]} are outside the videos (session "
                f"{bad[0][0]!r} has {by_name[bad[0][0]].num_frames} frames); pass the "
                f"--frames file made for these sessions"
            )
        seen: set[tuple[str, int]] = set()
        out = []
        for n, i in rows:
            if (n, i) not in seen:
                seen.add((n, i))
                out.append(Instant(n, i, _confidence(predictions.get(n), i)))
        return out
    if per_session < 1:
        raise LabelStartError(f"--n must be at least 1, got {per_session}")
    out = []
    for s in sessions:
        idx = np.unique(np.linspace(0, s.num_frames - 1, min(per_session, s.num_frames)).round())
        out += [Instant(s.name, int(i), _confidence(predictions.get(s.name), int(i))) for i in idx]
    return out


def open_store(
    inputs: Sequence[str | Path],
    calibration: Path,
    skeleton: str | Path,
    output: Path,
    *,
    frames: Path | None = None,
    poses_dir: Path | None = None,
    per_session: int = 20,
    settings: StoreSettings | None = None,
) -> LabelStore:
    """Check the inputs of ``freipose label`` and open its :class:`LabelStore`.

    Raises:
        LabelStartError, SessionError, MediaError, InputFileError, LabelsFormatError,
        SkeletonError, PosesFormatError: bad input (the message says how to fix it).
    """
    skel = load_skeleton(skeleton)
    sessions = discover_sessions(inputs, calibration, cameras="videos", need_fps=False)
    existing = status = None
    if Path(output).exists():
        existing = read_labels_h5(output)
        if existing.keypoints != skel.keypoints:
            raise LabelStartError(
                f"{output}: its keypoints {list(existing.keypoints)} differ from the skeleton "
                f"{skel.name!r} {list(skel.keypoints)}; pass the --skeleton these labels were "
                f"made with, or another -o file"
            )
        status = read_status(
            Path(output), (len(existing), len(existing.cameras), len(existing.keypoints))
        )
    preds = _predictions(sessions, poses_dir, skel)
    instants = choose_instants(sessions, frames, per_session, preds)
    return LabelStore(sessions, skel, instants, Path(output), existing, status, preds, settings)
