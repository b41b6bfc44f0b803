"""What every box source gives: candidate boxes with scores, per camera image."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from freipose.errors import FreiPoseError


class DetectConfigError(FreiPoseError):
    """A detection setting (a config value or a command-line option) is not allowed."""


@dataclass(frozen=True, eq=False)
class Candidates:
    """Candidate boxes in one camera image, best first.

    Attributes:
        boxes: (k, 4) ``(x0, y0, x1, y1)`` full-image pixels (k may be 0).
        scores: (k,) confidences in [0, 1].
    """

    boxes: np.ndarray
    scores: np.ndarray

    def __post_init__(self) -> None:
        b = np.asarray(self.boxes, dtype=np.float64).reshape(-1, 4)
        s = np.asarray(self.scores, dtype=np.float64).reshape(-1)
        if len(b) != len(s):
            raise ValueError(f"{len(b)} boxes but {len(s)} scores")
        order = np.argsort(-s, kind="stable")
        object.__setattr__(self, "boxes", b[order])
        object.__setattr__(self, "scores", s[order])

    def __len__(self) -> int:
        return len(self.scores)

    def top(self, k: int) -> Candidates:
        """The ``k`` best candidates."""
        return Candidates(self.boxes[:k], self.scores[:k])

    @staticmethod
    def empty() -> Candidates:
        """No candidates: boxes (0, 4), scores (0,)."""
        return Candidates(np.zeros((0, 4)), np.zeros(0))


@runtime_checkable
class BoxSource(Protocol):
    """Anything that proposes boxes: the trained detector, background subtraction, fixed boxes.

    ``propose(images, cameras)`` takes one BGR uint8 image (H, W, 3) per camera and the
    camera names (same order) and returns one :class:`Candidates` per image.
    """

    def propose(self, images: Sequence[np.ndarray], cameras: Sequence[str]) -> list[Candidates]:
        """One :class:`Candidates` per image (see the class docstring)."""
        ...
