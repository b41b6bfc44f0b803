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
from freipose.io.labels import LabelSet, read_labels_h5
from freipose.io.poses import PoseData, read_poses_h5
from freipose.io.session import Session, discover_sessions
from freipose.labels.select import read_selection_csv
from freipose.labelui.store import (
    Instant,
    LabelStore,
    StoreSettings,
    prediction_at,
    read_animals,
    read_status,
)
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


def _confidence(pred: PoseData | None, frame: int, animal: str = "") -> float:
    """Mean keypoint confidence of the prediction at ``frame`` (of ``animal``, if named)."""
    row = prediction_at(pred, frame, animal)
    if row is None:
        return float("nan")
    c = row[1]
    return float(np.nanmean(c)) if np.isfinite(c).any() else 0.0


def parse_animals(text: str) -> tuple[str, ...]:
    """The animals named by ``--animals``: a count (``animal_0``, ...) or names, comma-separated.

    A count names the animals as ``freipose predict --animals`` does, so that the labels
    and the predictions speak of the same animals.

    Raises:
        LabelStartError: a count below 1, an empty or repeated name.
    """
    text = text.strip()
    if text.isdigit():
        n = int(text)
        if n < 1:
            raise LabelStartError(f"--animals must be at least 1, got {n}")
        return tuple(f"animal_{a}" for a in range(n)) if n > 1 else ()
    names = tuple(a.strip() for a in text.split(","))
    if any(not a for a in names) or len(set(names)) != len(names):
        raise LabelStartError(
            f"--animals {text!r}: expected a number of animals or distinct names separated "
            f"by commas (e.g. --animals resident,intruder)"
        )
    return names


def _run_animals(
    given: Sequence[str] | None,
    existing: LabelSet | None,
    recorded: Sequence[str],
    predictions: dict[str, PoseData],
) -> tuple[str, ...]:
    """The animals to label: as given, else the labels file's, else the predictions'.

    The file's animals are those its labeling run recorded (``recorded``) followed by any
    other animal its rows name (imported labels).
    """
    if given is not None:
        return tuple(given)
    if existing is not None and (recorded or existing.individuals):
        return tuple(dict.fromkeys([*recorded, *existing.individuals]))
    names: dict[str, None] = {}
    for p in predictions.values():
        names.update(dict.fromkeys(p.individuals or ()))
    return tuple(names) if len(names) > 1 else ()


def per_animal(
    instants: Sequence[Instant], animals: Sequence[str], predictions: dict[str, PoseData]
) -> list[Instant]:
    """Each instant once per animal, the animals of one frame next to each other."""
    if not animals:
        return list(instants)
    return [
        Instant(x.session, x.frame, _confidence(predictions.get(x.session), x.frame, a), a)
        for x in instants
        for a in animals
    ]


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
    animals: Sequence[str] | None = None,
) -> LabelStore:
    """Check the inputs of ``freipose label`` and open its :class:`LabelStore`.

    ``animals`` names the animals to label at each instant (None: those of the labels
    file, else those of the predictions, else one animal; ``()``: one animal).

    Raises:
        LabelStartError, SessionError, MediaError, InputFileError, LabelsFormatError,
        SkeletonError, PosesFormatError: bad input (the message says how to fix it).
    """
    skel = load_skeleton(skeleton)
    sessions = discover_sessions(inputs, calibration, cameras="videos", need_fps=False)
    existing = status = None
    recorded: tuple[str, ...] = ()
    if Path(output).exists():
        existing = read_labels_h5(output)
        if existing.keypoints != skel.keypoints:
            raise LabelStartError(
                f"{output}: its keypoints {list(existing.keypoints)} differ from the skeleton "
                f"{skel.name!r} {list(skel.keypoints)}; pass the --skeleton these labels were "
                f"made with, or another -o file"
            )
        recorded = read_animals(Path(output))
        status = read_status(
            Path(output), (len(existing), len(existing.cameras), len(existing.keypoints))
        )
    preds = _predictions(sessions, poses_dir, skel)
    names = _run_animals(animals, existing, recorded, preds)
    if existing is not None and len(existing) and bool(existing.individuals) != bool(names):
        held = (
            f"the animals {list(existing.individuals)}"
            if existing.individuals
            else "one animal per instant"
        )
        asked = f"the animals {list(names)}" if names else "one animal"
        raise LabelStartError(
            f"{output}: it holds labels of {held}, and this run labels {asked}; pass "
            f"--animals as the file was made (or leave it out), or another -o file"
        )
    instants = per_animal(choose_instants(sessions, frames, per_session, preds), names, preds)
    return LabelStore(sessions, skel, instants, Path(output), existing, status, preds, settings)
