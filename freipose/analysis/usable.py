"""Variables undefined throughout a recording, and recordings without usable frames.

A keypoint that is missing (NaN) in every frame of a recording leaves every variable
computed from it undefined in that recording. Such a variable is left out of the whole
analysis (every group, so that all recordings keep the same variables) with a warning
naming the keypoints and the recording. A recording needs at least one *usable* frame:
labelled (not ignored) and with every remaining variable defined; otherwise the analysis
stops, because its scores would be computed on no frames at all.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from freipose.analysis.labelled import LabelledRecording
from freipose.analysis.study import IGNORED, StudyError
from freipose.analysis.variables import Variables

log = logging.getLogger(__name__)

SHOWN = 5  # variable names listed in a message


class NoUsableFramesError(StudyError):
    """Recordings leave no usable frames; the message names them, their keypoints and the fix."""


@dataclass(frozen=True)
class Undefined:
    """Variables of one recording that are NaN in every frame.

    Attributes:
        recording: the recording's name.
        poses: its poses file.
        columns: (V,) bool, the variables NaN in every frame.
        keypoints: keypoints whose every variable is NaN in every frame (missing throughout).
    """

    recording: str
    poses: str
    columns: np.ndarray
    keypoints: tuple[str, ...]

    def describe(self, names: tuple[str, ...]) -> str:
        """Say which keypoints and variables are undefined throughout the recording."""
        n = int(self.columns.sum())
        where = f"recording {self.recording!r} ({self.poses})"
        if self.keypoints:
            kps = ", ".join(repr(k) for k in self.keypoints)
            return (
                f"{where}: keypoint(s) {kps} missing (NaN) in every frame, so {n} of "
                f"{len(names)} variables are undefined throughout"
            )
        shown = [names[i] for i in np.flatnonzero(self.columns)[:SHOWN]]
        more = f" and {n - SHOWN} more" if n > SHOWN else ""
        return f"{where}: variables {shown}{more} are undefined (NaN) in every frame"


def undefined_variables(name: str, poses: str, var: Variables) -> Undefined:
    """Find the variables (and keypoints) of one recording that are NaN in every frame.

    Args:
        name: the recording's name.
        poses: its poses file, for messages.
        var: its variables.

    Returns:
        The undefined variables; a keypoint counts as missing when every variable that
        describes it (``parts``) is undefined.
    """
    cols = ~np.isfinite(var.values).any(axis=0)
    parts = np.asarray(var.parts)
    missing = tuple(kp for kp in var.keypoints if (parts == kp).any() and cols[parts == kp].all())
    return Undefined(name, poses, cols, missing)


def _fix(study_path: str | Path) -> str:
    return (
        f"check the predictions (poses file) of these recordings, or remove them from the "
        f"study file {study_path}"
    )


def _keep_columns(rec: LabelledRecording, keep: np.ndarray) -> LabelledRecording:
    var = rec.variables
    idx = np.flatnonzero(keep)

    def pick(seq: tuple[str, ...]) -> tuple[str, ...]:
        return tuple(seq[i] for i in idx)

    sub = dataclasses.replace(
        var,
        values=var.values[:, idx],
        names=pick(var.names),
        kinds=pick(var.kinds),
        components=pick(var.components),
        parts=pick(var.parts),
        involved=var.involved[idx],
    )
    return dataclasses.replace(rec, variables=sub)


def drop_undefined(
    recs: Mapping[str, LabelledRecording], study_path: str | Path = "STUDY.toml"
) -> dict[str, LabelledRecording]:
    """Leave out variables undefined throughout any recording; require usable frames.

    When no recording has such variables, the recordings come back unchanged. Every
    recording must keep at least one usable frame: labelled (not ignored) and with every
    remaining variable defined.

    Args:
        recs: recording name -> labelled recording (all with the same variables).
        study_path: the study file, for messages.

    Returns:
        Recording name -> the recording with only the variables defined somewhere in every
        recording.

    Raises:
        NoUsableFramesError: every variable is NaN throughout some recording, or a recording has
            no usable frame; the message names the recordings and keypoints.
    """
    undefined = [
        undefined_variables(name, str(r.recording.poses), r.variables) for name, r in recs.items()
    ]
    bad = [u for u in undefined if u.columns.any()]
    names = next(iter(recs.values())).variables.names
    drop = np.zeros(len(names), dtype=bool)
    for u in bad:
        drop |= u.columns
    if drop.all():
        raise NoUsableFramesError(
            "no variable left to analyze (each is NaN in every frame of some recording): "
            + "; ".join(u.describe(names) for u in bad)
            + "; "
            + _fix(study_path)
        )
    out = dict(recs)
    if bad:
        for u in bad:
            log.warning(
                "%s; these variables are left out of the whole analysis (no rows in "
                "attribution.csv); check the predictions of that recording or remove it from "
                "the study file",
                u.describe(names),
            )
        log.warning("%d of %d variables left out of the analysis", int(drop.sum()), len(names))
        out = {name: _keep_columns(r, ~drop) for name, r in recs.items()}
    _check_usable_frames(out, {u.recording: u for u in bad}, names, study_path)
    return out


def _check_usable_frames(
    recs: Mapping[str, LabelledRecording],
    undefined: Mapping[str, Undefined],
    names: tuple[str, ...],
    study_path: str | Path,
) -> None:
    """Raise unless every recording has a labelled frame with every variable defined."""
    empty = []
    for name, r in recs.items():
        usable = (r.labels != IGNORED) & np.isfinite(r.variables.values).all(axis=1)
        if not usable.any():
            why = f"recording {name!r} ({r.recording.poses})"
            if name in undefined:
                why = undefined[name].describe(names)
            empty.append(
                f"{why}, and none of its {r.variables.num_frames} frames is labelled (not "
                f"ignored) with all {r.variables.values.shape[1]} remaining variables defined"
            )
    if empty:
        raise NoUsableFramesError("no usable frames: " + "; ".join(empty) + "; " + _fix(study_path))
