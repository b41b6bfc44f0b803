"""What every demo step shares: the run's paths and settings, and the true-world mapping."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from freipose.demo.presets import DemoPreset

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from freipose.io.labels import LabelSet


@dataclass(frozen=True)
class DemoContext:
    """Paths and settings shared by the steps of one demo run.

    Attributes:
        out: the demo folder.
        preset: the run's sizes.
        device: torch device for training and prediction.
        say: where progress messages go.
        progress: progress bars (None: only on a terminal).
    """

    out: Path
    preset: DemoPreset
    device: str = "cpu"
    say: Callable[[str], None] = print
    progress: bool | None = None

    @property
    def recordings(self) -> Path:
        """The folder of the synthetic recordings."""
        return self.out / "recordings"

    def session_dir(self, name: str) -> Path:
        """The folder of the session ``name`` (videos, labels, events)."""
        return self.recordings / name

    @property
    def calib_videos(self) -> Path:
        """The folder of the board videos (in the first session)."""
        return self.session_dir(self.preset.sessions[0].name) / "calibration"

    @property
    def calibration(self) -> Path:
        """The calibrated rig, ``calibration/calibration.toml``."""
        return self.out / "calibration" / "calibration.toml"

    @property
    def train_dir(self) -> Path:
        """The folder of the training configs and runs."""
        return self.out / "train"

    @property
    def poses_dir(self) -> Path:
        """The folder of the predicted ``<session>.poses.h5`` files."""
        return self.out / "poses"


def truth_to_calibrated(points: np.ndarray, alignment: dict[str, Any]) -> np.ndarray:
    """Map true world points into the calibrated world frame (inverse alignment).

    Args:
        points: (..., 3) points in the true world frame (mm).
        alignment: ``scale``, ``R`` (3, 3) and ``t`` (3,) mapping calibrated to true world
            coordinates (as in the ``calibrate`` step's results).

    Returns:
        (..., 3) the points in the calibrated world frame.
    """
    R = np.asarray(alignment["R"])
    t = np.asarray(alignment["t"])
    return ((points - t) @ R) / float(alignment["scale"])


def session_labels(ctx: DemoContext, name: str) -> LabelSet:
    """The true labels (2D and 3D keypoints of every frame) of the synthetic session ``name``."""
    from freipose.io.labels import read_labels_h5

    return read_labels_h5(ctx.session_dir(name) / "labels.h5")


def save_png(fig: Figure, path: Path) -> None:
    """Write a demo figure to ``path`` (PNG at 90 dpi, tight bounding box; atomically)."""
    from freipose.io.figures import save_figure

    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, dpi=90, format="png", bbox_inches="tight")
