"""A board at rest over several frames counts as one view.

Consecutive frames of a board lying still (for the origin frame on the floor, or a pause
while recording) repeat one pose: their corners differ only by image noise, while the
corner refinement's error for that pose (a bias of a few hundredths of a pixel, larger at
steep angles) is the same in all of them. Counted n times, that one view pulls the
solution n times as hard as any other. :func:`merge_static_runs` replaces each run of
frames in which no camera's corners moved by one frame holding the run's mean corners.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from freipose.calibration.detect import CameraDetections

__all__ = ["STILL_PX", "StaticRuns", "merge_static_runs"]

STILL_PX = 0.3  # corners that moved less than this between frames: the board was at rest


@dataclass(frozen=True)
class StaticRuns:
    """The detections with each run of identical board poses merged into one frame.

    Attributes:
        detections: per camera, the detections (same frames; merged frames are NaN).
        runs: ``(first, last, kept)`` frame of each run of two or more still frames.
    """

    detections: list[CameraDetections]
    runs: tuple[tuple[int, int, int], ...]

    @property
    def frames_merged(self) -> int:
        """How many frames were folded into another frame of their run."""
        return sum(b - a for a, b, _ in self.runs)


def _still(dets: Sequence[CameraDetections], f: int) -> bool:
    """Frame ``f`` shows the board where frame ``f - 1`` did, in every camera."""
    seen = False
    for d in dets:
        a, b = d.mask[f - 1], d.mask[f]
        if not np.array_equal(a, b):
            return False
        if b.any():
            seen = True
            step = np.linalg.norm(d.points[f, b] - d.points[f - 1, b], axis=1)
            if step.max() >= STILL_PX:
                return False
    return seen


def merge_static_runs(dets: Sequence[CameraDetections], keep: int | None = None) -> StaticRuns:
    """Merge every run of consecutive still frames into one frame (the run's mean corners).

    Args:
        dets: per camera, the detections (the same frames).
        keep: a frame that must stay (``--origin-frame``): a run holding it is merged
            into it; other runs into their first frame.

    Returns:
        The merged detections and the runs.
    """
    F = dets[0].num_frames if dets else 0
    still = np.array([False] + [_still(dets, f) for f in range(1, F)], dtype=bool)
    runs = []
    f = 1
    while f < F:
        if not still[f]:
            f += 1
            continue
        a = f - 1
        while f < F and still[f]:
            f += 1
        b = f - 1
        runs.append((a, b, keep if keep is not None and a <= keep <= b else a))
    if not runs:
        return StaticRuns(list(dets), ())
    out = []
    for d in dets:
        pts = d.points.copy()
        for a, b, k in runs:
            mean = np.mean(d.points[a : b + 1], axis=0)  # NaN stays NaN: same mask in the run
            pts[a : b + 1] = np.nan
            pts[k] = mean
        out.append(replace(d, points=pts))
    return StaticRuns(out, tuple(runs))
