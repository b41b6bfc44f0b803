"""The voxel cube and the crops sized from the training labels (``[model] cube_size = "auto"``).

The cube is centred on the labeled keypoints' mean (in training) or on the detected
centre (in prediction), so it must hold the animal around that centre: its edge is twice
the ``percentile`` (99th) of the animal's radius over the training instants (the largest
distance of a labeled keypoint from the instant's centre), plus a ``margin`` (25 %) for
the centre's errors and the augmentation's jitter, rounded up to ``step`` (10 mm). The
voxel size follows (edge / (grid_size - 1)); the crops enclose the projection of a
``crop_fraction * cube_size`` cube around the centre, so they scale with the cube and keep
the preset's share of the cube. A synthetic rat gives 330 mm (its radius is 130 mm), a
mouse about half.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import numpy as np

from freipose.errors import FreiPoseError
from freipose.geometry.crops import cube_crop_boxes, label_centers
from freipose.io.labels import LabelSet
from freipose.nn.config import ModelConfig, TrainConfig

log = logging.getLogger(__name__)

PERCENTILE = 99.0
MARGIN = 0.25
STEP = 10.0


class SizingError(FreiPoseError):
    """The cube cannot be sized from the labels (the message says why and what to set)."""


@dataclass(frozen=True)
class CubeSizing:
    """The cube chosen from the labels and the numbers it came from.

    Attributes:
        cube_size: mm between the outermost voxel centres.
        radius: the ``percentile`` of the animal's radius over the instants (mm).
        percentile: which percentile.
        margin: the relative margin added to the radius.
        instants: labeled instants with at least two 3D keypoints that were used.
        voxel_size: mm between voxel centres.
        crop_cube: edge (mm) of the cube whose projection each crop encloses.
        crop_pixels: median side (image pixels) of that projection over the labels' views,
            NaN without calibrated views; the crops are resampled to ``crop_size`` pixels.
    """

    cube_size: float
    radius: float
    percentile: float
    margin: float
    instants: int
    voxel_size: float
    crop_cube: float
    crop_pixels: float

    def describe(self, crop_size: int) -> str:
        """One line for the log: the chosen values and where they came from."""
        px = (
            f", about {self.crop_pixels:.0f} image px wide, resampled to {crop_size} px"
            if math.isfinite(self.crop_pixels)
            else ""
        )
        return (
            f"cube {self.cube_size:.0f} mm from the training labels (the {self.percentile:g}th "
            f"percentile of the animal's radius around its centre, {self.radius:.1f} mm over "
            f"{self.instants} instants, + {self.margin:.0%}), voxel {self.voxel_size:.2f} mm; "
            f"crops enclose a {self.crop_cube:.0f} mm cube{px}"
        )


def animal_radius(points3d: np.ndarray, percentile: float = PERCENTILE) -> tuple[float, int]:
    """The ``percentile`` of the animal's radius over labeled instants.

    Args:
        points3d: (N, K, 3) mm, NaN = unlabeled.
        percentile: in (0, 100].

    Returns:
        ``(radius mm, instants used)``: per instant with >= 2 labeled keypoints the largest
        distance of a keypoint from their mean.
    """
    p = np.asarray(points3d, dtype=np.float64)
    ok = np.isfinite(p).all(-1)  # (N, K)
    use = ok.sum(1) >= 2
    if not use.any():
        return float("nan"), 0
    p, ok = p[use], ok[use]
    centre = label_centers(p)
    dist = np.where(ok, np.linalg.norm(np.nan_to_num(p) - centre[:, None], axis=-1), 0.0)
    return float(np.percentile(dist.max(1), percentile)), int(use.sum())


def _crop_pixels(labels: LabelSet, crop_cube: float, most: int = 200) -> float:
    """Median side (px) of the crop cube's projection at the labels' centres."""
    sides = []
    rows = np.flatnonzero(np.isfinite(labels.points3d).all(-1).any(-1))
    if len(rows) > most:
        rows = rows[np.linspace(0, len(rows) - 1, most).round().astype(int)]
    for sess in sorted(set(labels.session[rows])):
        rig = labels.rig_for(sess)
        if rig is None:
            continue
        sel = rows[labels.session[rows] == sess]
        centres = np.nanmean(labels.points3d[sel], axis=1)  # (n, 3)
        boxes = cube_crop_boxes(rig, centres, crop_cube)  # (n, C, 4)
        sides.append((boxes[..., 2] - boxes[..., 0]).ravel())
    s = np.concatenate(sides) if sides else np.zeros(0)
    s = s[np.isfinite(s)]
    return float(np.median(s)) if len(s) else float("nan")


def size_cube(
    labels: LabelSet,
    model: ModelConfig,
    percentile: float = PERCENTILE,
    margin: float = MARGIN,
    step: float = STEP,
) -> CubeSizing:
    """The cube (and crops) for ``model`` from the extent of the labeled animal.

    Args:
        labels: the training labels (3D keypoints in mm).
        model: the model config (grid size, crop fraction, kind).
        percentile: of the animal's radius over the instants.
        margin: relative margin on the radius.
        step: the edge is rounded up to a multiple of this (mm).

    Returns:
        The sizing.

    Raises:
        SizingError: no instant has two labeled 3D keypoints.
    """
    radius, n = animal_radius(labels.points3d, percentile)
    if n == 0 or not radius > 0:
        raise SizingError(
            'model.cube_size is "auto" but no training instant has two labeled 3D keypoints '
            "to size the cube from; set model.cube_size (mm) in the config"
        )
    cube = float(math.ceil(2 * radius * (1 + margin) / step) * step)
    sized = dataclasses.replace(model, cube_size=cube)
    return CubeSizing(
        cube_size=cube,
        radius=radius,
        percentile=percentile,
        margin=margin,
        instants=n,
        voxel_size=sized.voxel_size,
        crop_cube=sized.crop_cube,
        crop_pixels=_crop_pixels(labels, sized.crop_cube),
    )


def resolve_cube(config: TrainConfig, labels: LabelSet) -> TrainConfig:
    """``config`` with the cube sized from ``labels`` when it asks for it (``cube_auto``).

    The chosen values are logged and written into the config (so into ``config.toml`` and
    every checkpoint); an explicit ``model.cube_size`` is kept as it is.

    Args:
        config: the resolved training config.
        labels: the training labels.

    Returns:
        The config to train with.
    """
    if not getattr(config, "cube_auto", False):
        log.info(
            "cube %.0f mm (model.cube_size), voxel %.2f mm; crops enclose a %.0f mm cube",
            config.model.cube_size,
            config.model.voxel_size,
            config.model.crop_cube,
        )
        return config
    sizing = size_cube(labels, config.model)
    log.info("%s", sizing.describe(config.model.crop_size))
    model = dataclasses.replace(config.model, cube_size=sizing.cube_size)
    return dataclasses.replace(config, model=model, cube_auto=False)
