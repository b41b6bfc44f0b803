"""The errors of the synthetic scene generator (all :class:`~freipose.errors.FreiPoseError`)."""

from __future__ import annotations

from freipose.errors import FreiPoseError


class SynthError(FreiPoseError):
    """A scene, animal, arena, stimulation or rig setting that is out of range or unknown."""


class RigFileError(SynthError):
    """A rig file is malformed; the message names the file, the entry and the problem."""


__all__ = ["RigFileError", "SynthError"]
