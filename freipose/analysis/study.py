"""Study manifest ``STUDY.toml``, stimulation events ``events.csv`` and frame labelling.

STUDY.toml (paths relative to the study file)::

    skeleton = "rat"                  # optional: name or path (default: the poses' own)

    [[recordings]]
    name = "rat1_day1"
    poses = "rat1_day1.poses.h5"
    events = "rat1_day1_events.csv"   # columns start_s,end_s (seconds from the first frame)
    animal = "rat1"
    condition = "10Hz"
    split = "train"                   # or "test"
    floor = "auto"                    # optional: world | auto | floor TOML (default: --floor)

events.csv: a header ``start_s,end_s`` and one row per stimulation window; windows must lie
inside the recording and must not overlap. A file with only the header means "never
stimulated" (a control recording).
"""

from __future__ import annotations

import csv
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from freipose.errors import FreiPoseError, InputFileError
from freipose.io.toml import check_keys, read_toml

log = logging.getLogger(__name__)

RECORDING_KEYS = ("name", "poses", "events", "animal", "condition", "split", "floor")
TOP_KEYS = ("recordings", "skeleton", "name", "description")
REQUIRED_KEYS = ("name", "poses", "events", "animal", "condition", "split")
SPLITS = ("train", "test")
STIMULATED, NOT_STIMULATED, IGNORED = 1, 0, -1
EVENTS_FIX = "one row per stimulation window, seconds from the first frame of the poses file"


class StudyError(FreiPoseError):
    """A study manifest or events file is invalid; the message says what and how to fix it."""


@dataclass(frozen=True)
class Recording:
    """One recording of a study (paths resolved against the study file's folder)."""

    name: str
    poses: Path
    events: Path
    animal: str
    condition: str
    split: str
    floor: str | None = None


@dataclass(frozen=True)
class Study:
    """A study: recordings grouped by (animal, condition), each in the train or test split."""

    path: Path
    recordings: tuple[Recording, ...]
    skeleton: str | None = None

    @property
    def groups(self) -> list[tuple[str, str]]:
        """(animal, condition) pairs in order of first appearance."""
        seen: dict[tuple[str, str], None] = {}
        for r in self.recordings:
            seen.setdefault((r.animal, r.condition), None)
        return list(seen)

    def select(self, animal: str, condition: str, split: str) -> list[Recording]:
        """The recordings of one group in one split, in study order.

        Args:
            animal: the animal.
            condition: the condition.
            split: ``"train"`` or ``"test"``.

        Returns:
            The matching recordings.
        """
        return [
            r
            for r in self.recordings
            if r.animal == animal and r.condition == condition and r.split == split
        ]


def recording_entry(
    name: str, poses: str, events: str, animal: str, condition: str, split: str
) -> str:
    """One ``[[recordings]]`` table of a study manifest, as TOML text ending in a newline.

    Args:
        name: the recording's name.
        poses: its poses file (relative to the manifest, or absolute).
        events: its events file (likewise).
        animal: its animal.
        condition: its condition.
        split: ``"train"`` or ``"test"``.

    Returns:
        The table; the values are TOML basic strings (quotes and backslashes escaped).
    """
    values = dict(name=name, poses=poses, events=events, animal=animal, condition=condition,
                  split=split)  # fmt: skip
    return "[[recordings]]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in values.items())


def _floor_entry(value: object, base: Path) -> str | None:
    if value is None:
        return None
    return str(value) if str(value) in ("world", "auto") else str(base / str(value))


def _recording(r: object, where: str, base: Path, check_files: bool) -> Recording:
    """One ``[[recordings]]`` table as a recording (paths resolved against ``base``).

    Args:
        r: the table.
        where: the study file and the table's position, for messages.
        base: the study file's folder.
        check_files: whether the poses and events files must exist.

    Returns:
        The recording.

    Raises:
        StudyError: not a table, a missing or unknown key, or a bad split.
        InputFileError: a poses or events file does not exist (with ``check_files``).
    """
    if not isinstance(r, dict):
        raise StudyError(f"{where}: expected a [[recordings]] table")
    missing = [k for k in REQUIRED_KEYS if k not in r]
    if missing:
        raise StudyError(f"{where} ({r.get('name', '?')}): missing keys {missing}")
    check_keys(r, RECORDING_KEYS, where, StudyError)
    split = str(r["split"])
    if split not in SPLITS:
        raise StudyError(f"{where} ({r['name']}): split must be 'train' or 'test', not {split!r}")
    rec = Recording(
        name=str(r["name"]),
        poses=base / str(r["poses"]),
        events=base / str(r["events"]),
        animal=str(r["animal"]),
        condition=str(r["condition"]),
        split=split,
        floor=_floor_entry(r.get("floor"), base),
    )
    if check_files:
        for what, p in (("poses", rec.poses), ("events", rec.events)):
            if not p.is_file():
                raise InputFileError(
                    f"{where} ({rec.name}): {what} file not found: {p} (paths are relative "
                    f"to the study file's folder {base})"
                )
    return rec


def _check_groups(study: Study) -> None:
    """Raise unless recording names are unique and every group has train and test recordings.

    Args:
        study: the study read so far.

    Raises:
        StudyError: a repeated name, or a group without a train or test recording.
    """
    path = study.path
    names = [r.name for r in study.recordings]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise StudyError(f"study file {path}: recording names must be unique; repeated: {dupes}")
    for animal, cond in study.groups:
        for split in SPLITS:
            if not study.select(animal, cond, split):
                raise StudyError(
                    f"study file {path}: group (animal {animal!r}, condition {cond!r}) has no "
                    f"{split} recording; every group needs at least one recording with "
                    f"split = 'train' and one with split = 'test'"
                )


def load_study(path: str | Path, check_files: bool = True) -> Study:
    """Read and validate ``STUDY.toml``.

    Every (animal, condition) group needs at least one train and one test recording.

    Args:
        path: the study file.
        check_files: whether the poses and events files must exist.

    Returns:
        The study.

    Raises:
        InputFileError: the study file (or, with ``check_files``, a recording's file) does
            not exist.
        StudyError: the file is not valid TOML or breaks a rule above.
    """
    path = Path(path)
    data = read_toml(path, "study file", StudyError)
    check_keys(data, TOP_KEYS, f"study file {path}", StudyError)
    recs = data.get("recordings")
    if not isinstance(recs, list) or not recs:
        raise StudyError(
            f"study file {path}: no recordings; add [[recordings]] tables with keys "
            f"{list(REQUIRED_KEYS)}"
        )
    base = path.parent
    out = tuple(
        _recording(r, f"study file {path}: recording {i + 1}", base, check_files)
        for i, r in enumerate(recs)
    )
    study = Study(path, out, None if "skeleton" not in data else str(data["skeleton"]))
    _check_groups(study)
    return study


def _event_rows(path: Path) -> tuple[list[tuple[float, float]], list[int]]:
    """The windows of an events file and the line of each (unsorted, unchecked).

    Raises:
        StudyError: not CSV text, missing columns or non-numeric values.
    """
    rows: list[tuple[float, float]] = []
    lines: list[int] = []
    try:
        with path.open(newline="") as fh:
            reader = csv.DictReader(fh)
            cols = [c.strip() for c in (reader.fieldnames or [])]
            if "start_s" not in cols or "end_s" not in cols:
                raise StudyError(
                    f"events file {path}, line 1: expected a header with columns start_s,end_s "
                    f"({EVENTS_FIX}), found {cols}; add or correct the header"
                )
            for row in reader:
                line = reader.line_num
                row = {k.strip(): v for k, v in row.items() if k is not None}
                if all(not (v or "").strip() for v in row.values()):
                    continue
                try:
                    rows.append((float(row["start_s"]), float(row["end_s"])))
                except (TypeError, ValueError):
                    raise StudyError(
                        f"events file {path}, line {line}: start_s/end_s must be numbers "
                        f"(seconds), got {row.get('start_s')!r}, {row.get('end_s')!r}; correct "
                        f"or remove that row"
                    ) from None
                lines.append(line)
    except (UnicodeDecodeError, csv.Error) as exc:
        raise StudyError(
            f"events file {path}: not a readable CSV text file ({exc}); expected a header "
            f"start_s,end_s and {EVENTS_FIX}"
        ) from None
    return rows, lines


def read_event_windows(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read and check ``events.csv``, keeping the file line of every window.

    Args:
        path: the events file.

    Returns:
        (N, 2) float start/end seconds sorted by start, and (N,) their lines in the file.

    Raises:
        InputFileError: no such file.
        StudyError: not CSV text, missing columns, non-numeric or non-finite values,
            end <= start, overlapping windows; the message names the file, the line and the
            fix.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"events file not found: {path}")
    rows, lines = _event_rows(path)
    win = np.array(rows, dtype=float).reshape(-1, 2)
    line = np.array(lines, dtype=np.int64)
    for i in range(len(win)):
        a, b = win[i]
        if not (np.isfinite(a) and np.isfinite(b)):
            raise StudyError(
                f"events file {path}, line {line[i]}: start_s/end_s must be finite numbers, "
                f"got {a}, {b}; correct or remove that row"
            )
        if b <= a:
            raise StudyError(
                f"events file {path}, line {line[i]}: the window ends ({b} s) before it starts "
                f"({a} s); end_s must be greater than start_s (swapped columns?)"
            )
    order = np.argsort(win[:, 0], kind="stable")
    win, line = win[order], line[order]
    over = np.flatnonzero(win[1:, 0] < win[:-1, 1])
    if len(over):
        i = over[0]
        raise StudyError(
            f"events file {path}, lines {line[i]} and {line[i + 1]}: windows overlap: "
            f"[{win[i, 0]}, {win[i, 1]}] s and [{win[i + 1, 0]}, {win[i + 1, 1]}] s; merge or "
            f"correct them"
        )
    return win, line


def read_events(path: str | Path) -> np.ndarray:
    """Read ``events.csv``.

    Args:
        path: the events file.

    Returns:
        (N, 2) float start/end seconds, sorted by start.

    Raises:
        InputFileError: no such file.
        StudyError: see :func:`read_event_windows`.
    """
    return read_event_windows(path)[0]


def check_windows(
    windows: np.ndarray, duration_s: float, source: str, lines: np.ndarray | None = None
) -> None:
    """Raise when a window lies outside ``[0, duration_s]`` (seconds from the first frame).

    Args:
        windows: (N, 2) start/end seconds.
        duration_s: the recording's duration in seconds.
        source: the events file and recording, for messages.
        lines: (N,) the windows' lines in the events file, for messages.

    Raises:
        StudyError: a window lies outside the recording.
    """
    win = np.asarray(windows).reshape(-1, 2)
    tol = 1e-6
    bad = np.flatnonzero((win[:, 0] < -tol) | (win[:, 1] > duration_s + tol))
    if len(bad):
        a, b = win[bad[0]]
        where = f"{source}, line {lines[bad[0]]}" if lines is not None else source
        what = "stimulation window" if lines is not None else f"stimulation window {bad[0] + 1}"
        raise StudyError(
            f"{where}: {what} [{a}, {b}] s lies outside the recording "
            f"(0 to {duration_s:.3f} s from the first frame); events are seconds from the "
            f"first frame of the poses file, not from the start of the video or clock time; "
            f"correct or remove that row"
        )


def poses_duration(path: str | Path) -> float | None:
    """Duration in seconds of a poses file's frame range, read without loading the poses.

    Args:
        path: the poses file.

    Returns:
        ``(last frame - first frame + 1) / fps`` (the duration of its variables), or None
        when the file does not say (its reader reports the problem later).
    """
    try:
        with h5py.File(path, "r") as f:
            fps = float(f.attrs["fps"])
            fi = np.asarray(f["frame_index"][()], dtype=np.int64)
    except (OSError, KeyError, ValueError, TypeError):
        return None
    if fi.ndim != 1 or not len(fi) or not (np.isfinite(fps) and fps > 0):
        return None
    return float(fi[-1] - fi[0] + 1) / fps


def check_study_events(study: Study) -> None:
    """Check every recording's events file before any variable is computed.

    Each file must parse (see :func:`read_event_windows`) and its windows must lie inside
    the recording, whose duration comes from the poses file's frame range and frame rate.

    Args:
        study: the study.

    Raises:
        StudyError: invalid events files; the message names every bad file, its line and
            the fix.
        InputFileError: an events file does not exist.
    """
    problems: dict[str, StudyError] = {}
    for rec in study.recordings:
        try:
            win, lines = read_event_windows(rec.events)
            duration = poses_duration(rec.poses)
            if duration is not None:
                check_windows(win, duration, f"events file {rec.events} ({rec.name})", lines)
        except StudyError as exc:
            problems.setdefault(str(exc), exc)
    if len(problems) == 1:
        raise next(iter(problems.values()))
    if problems:
        raise StudyError(
            f"{len(problems)} events problems in study {study.path}:\n"
            + "\n".join(f"  - {m}" for m in problems)
        )


def label_frames(
    times: np.ndarray, windows: np.ndarray, onset_delay_s: float = 0.4, margin_s: float = 1.5
) -> np.ndarray:
    """Label frames stimulated (1), not stimulated (0) or ignored (-1).

    Stimulated: ``start + onset_delay <= t <= end`` for some window. Not stimulated: further
    than ``margin_s`` from every window (``t < start - margin`` or ``t > end + margin``).
    Everything else (the onset delay and the margins) is ignored.

    Args:
        times: (T,) seconds from the first frame.
        windows: (N, 2) sorted, non-overlapping start/end seconds.
        onset_delay_s: seconds after a window's start before frames count as stimulated.
        margin_s: seconds around a window whose frames are ignored.

    Returns:
        (T,) int8 labels.

    Raises:
        StudyError: a negative delay or margin.
    """
    if onset_delay_s < 0 or margin_s < 0:
        raise StudyError("onset delay and margin must be >= 0 seconds")
    t = np.asarray(times, dtype=float)
    win = np.asarray(windows, dtype=float).reshape(-1, 2)
    labels = np.full(t.shape, NOT_STIMULATED, dtype=np.int8)
    if not len(win):
        return labels
    i = np.searchsorted(win[:, 0], t, side="right") - 1  # last window starting at or before t
    has = i >= 0
    ic = np.clip(i, 0, len(win) - 1)
    stim = has & (t >= win[ic, 0] + onset_delay_s) & (t <= win[ic, 1])
    near_prev = has & (t <= win[ic, 1] + margin_s)
    nxt = np.clip(i + 1, 0, len(win) - 1)
    near_next = (i + 1 < len(win)) & (t >= win[nxt, 0] - margin_s)
    labels[near_prev | near_next] = IGNORED
    labels[stim] = STIMULATED
    return labels
