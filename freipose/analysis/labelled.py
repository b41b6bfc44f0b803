"""Recordings of a study with their variables, stimulation windows and frame labels."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from freipose.analysis.config import AttributionConfig
from freipose.analysis.stats import standardize_recording
from freipose.analysis.study import (
    IGNORED,
    NOT_STIMULATED,
    STIMULATED,
    Recording,
    Study,
    StudyError,
    check_windows,
    label_frames,
    read_event_windows,
)
from freipose.analysis.variables import Variables


@dataclass(frozen=True, eq=False)
class LabelledRecording:
    """A recording's variables, stimulation windows and frame labels.

    Attributes:
        recording: the study entry.
        variables: its (T, V) variables.
        windows: (W, 2) stimulation windows in seconds from the first frame.
        labels: (T,) frame labels (stimulated, not stimulated or ignored).
    """

    recording: Recording
    variables: Variables
    windows: np.ndarray
    labels: np.ndarray


@dataclass(frozen=True)
class Frames:
    """Labelled frames of several recordings, concatenated in time order.

    Attributes:
        values: (N, V) variables.
        labels: (N,) int8 labels in {0, 1}.
        recording: (N,) index of each frame's recording.
    """

    values: np.ndarray
    labels: np.ndarray
    recording: np.ndarray


def label_recordings(
    study: Study, variables: Mapping[str, Variables], config: AttributionConfig
) -> dict[str, LabelledRecording]:
    """Read the events of every recording, check them and label the frames.

    Args:
        study: the validated study.
        variables: recording name -> its variables.
        config: the onset delay and margin of the labelling.

    Returns:
        Recording name -> its labelled recording, in study order.

    Raises:
        StudyError: recordings with different variables, or invalid events.
    """
    names = None
    fps = None
    out = {}
    for rec in study.recordings:
        var = variables[rec.name]
        if names is None:
            names, fps, first = var.names, var.fps, rec.name
        elif var.names != names:
            raise StudyError(
                f"recordings {first!r} and {rec.name!r} have different variables (different "
                f"skeletons, STFT settings or frame rates: {fps} vs {var.fps} fps); all "
                f"recordings of a study must give the same variables"
            )
        win, lines = read_event_windows(rec.events)
        source = f"events file {rec.events} ({rec.name})"
        check_windows(win, var.num_frames / var.fps, source, lines)
        labels = label_frames(var.times, win, config.onset_delay_s, config.margin_s)
        out[rec.name] = LabelledRecording(rec, var, win, labels)
    return out


def check_test_classes(recs: Mapping[str, LabelledRecording]) -> None:
    """Check that every animal's test recordings of a condition hold frames of both classes.

    A balanced accuracy (and the F1 of the stimulated class) is undefined on frames of one
    class: test recordings whose events files hold no stimulation window that fits, or
    whose windows leave no frame outside the margins, cannot be scored.

    Args:
        recs: recording name -> labelled recording.

    Raises:
        StudyError: the (animal, condition) pairs whose test frames lack a class, with their
            recordings and counts.
    """
    groups: dict[tuple[str, str], list[LabelledRecording]] = {}
    for r in recs.values():
        if r.recording.split == "test":
            groups.setdefault((r.recording.animal, r.recording.condition), []).append(r)
    bad = []
    for (animal, cond), rs in groups.items():
        labels = np.concatenate([r.labels for r in rs])
        n_stim, n_not = int((labels == STIMULATED).sum()), int((labels == NOT_STIMULATED).sum())
        if n_stim == 0 or n_not == 0:
            names = ", ".join(repr(r.recording.name) for r in rs)
            events = ", ".join(str(r.recording.events) for r in rs)
            bad.append(
                f"animal {animal!r}, condition {cond!r}: the test recordings ({names}) have "
                f"{n_stim} stimulated and {n_not} not-stimulated frames (events: {events})"
            )
    if bad:
        raise StudyError(
            "a balanced accuracy needs test frames of both classes, stimulated and not: "
            + "; ".join(bad)
            + "; give the test recordings events files with their stimulation windows "
            "(and time without stimulation), check --onset-delay and --margin, or leave "
            "those recordings out of the study"
        )


def standardized(
    recs: Mapping[str, LabelledRecording], rtol: float
) -> dict[str, LabelledRecording]:
    """Copies of the recordings with every variable z-scored per recording.

    Args:
        recs: recording name -> labelled recording.
        rtol: columns constant up to this relative deviation become 0
            (:func:`~freipose.analysis.stats.standardize_recording`).

    Returns:
        Recording name -> the recording with standardized values.
    """
    return {
        name: dataclasses.replace(
            r,
            variables=dataclasses.replace(
                r.variables, values=standardize_recording(r.variables.values, rtol)
            ),
        )
        for name, r in recs.items()
    }


def stack_frames(recs: Sequence[LabelledRecording], stride: int = 1) -> Frames:
    """Labelled (not ignored) frames of several recordings.

    Args:
        recs: the recordings, in order.
        stride: use every n-th labelled frame of each recording.

    Returns:
        Their values, labels and recording indices.
    """
    xs, ys, ids = [], [], []
    for i, r in enumerate(recs):
        keep = np.flatnonzero(r.labels != IGNORED)[::stride]
        xs.append(r.variables.values[keep])
        ys.append(r.labels[keep])
        ids.append(np.full(len(keep), i, dtype=np.int64))
    return Frames(np.concatenate(xs), np.concatenate(ys).astype(np.int8), np.concatenate(ids))


def longest_window(recs: Mapping[str, LabelledRecording]) -> float:
    """Duration in seconds of the longest stimulation window of any recording (0 if none).

    Args:
        recs: recording name -> labelled recording.

    Returns:
        The duration in seconds.
    """
    return max(
        (float(np.max(r.windows[:, 1] - r.windows[:, 0])) for r in recs.values() if len(r.windows)),
        default=0.0,
    )
