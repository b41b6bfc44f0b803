"""Poses of several animals: joining single-animal poses into a file with an animal axis.

The animal axis of ``poses.h5`` is described in :mod:`freipose.io.poses`; one animal of such
poses is ``PoseData.animal(name)``.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from freipose.io.poses import ANIMAL_EXTRAS, PoseData, PosesFormatError


def stack_animals(
    animals: Mapping[str, PoseData], identity_confidence: np.ndarray | None = None
) -> PoseData:
    """Join single-animal poses of one recording into poses with an animal axis.

    Args:
        animals: name -> that animal's poses (same frames, keypoints and fps); the first
            one gives the calibration, skeleton, up and provenance.
        identity_confidence: (T, A) in [0, 1], or None.

    Returns:
        Poses (T, A, K, 3) with ``individuals`` the names in order; extras that every
        animal has are stacked (per-animal ones) or taken from the first (per-frame ones).

    Raises:
        PosesFormatError: no animal, an animal with an axis of its own, or animals whose
            frames or keypoints differ.
    """
    items = list(animals.items())
    if not items:
        raise PosesFormatError("stack_animals needs at least one animal")
    first = items[0][1]
    for name, d in items:
        if d.individuals is not None:
            raise PosesFormatError(f"animal {name!r} has an animal axis of its own")
        if d.keypoints != first.keypoints or not np.array_equal(d.frame_index, first.frame_index):
            raise PosesFormatError(
                f"animal {name!r} has other keypoints or frames than {items[0][0]!r}"
            )
    shared = [k for k in first.extra if all(k in d.extra for _, d in items)]
    extra = {
        k: (np.stack([d.extra[k] for _, d in items], 1) if k in ANIMAL_EXTRAS else first.extra[k])
        for k in shared
    }  # fmt: skip
    prov = {k: v for k, v in first.provenance.items() if k != "individual"}
    return PoseData(
        np.stack([d.poses for _, d in items], 1), np.stack([d.confidence for _, d in items], 1),
        first.keypoints, first.frame_index, first.fps, first.up, first.calibration,
        first.skeleton, prov, extra, tuple(n for n, _ in items), identity_confidence,
    )  # fmt: skip


__all__ = ["stack_animals"]
