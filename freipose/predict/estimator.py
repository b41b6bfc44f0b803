"""The interface between the prediction loop and whatever turns frames into 3D poses.

The loop (``freipose.predict.run``) only needs a :class:`PoseEstimator`: a callable on a
batch of synchronized full frames and the rig of those cameras that returns an
:class:`Estimate`. ``freipose.predict.network.NetworkEstimator`` is the real one (detector
plus voxel network). An estimator must be a pure function of each time step's frames (no
state carried between calls), so that a resumed or sharded run gives the same numbers.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from freipose.geometry.camera import CameraRig


@dataclass(frozen=True, eq=False)
class Estimate:
    """Predictions for B time steps, C cameras, K keypoints.

    Attributes:
        poses: (B, K, 3) world mm, NaN where not found.
        confidence: (B, K) in [0, 1], 0 where not found.
        points2d: (B, C, K, 2) per-view 2D keypoints, full-image pixels, NaN if unknown.
        confidence2d: (B, C, K) per-view confidences in [0, 1], 0 if unknown.
        boxes: (B, C, 4) crop boxes (x0, y0, x1, y1) in full-image pixels, NaN if none.
        center: (B, 3) world mm centre of the 3D grid, NaN where the animal was not found.
        uncertainty: (B, K) calibrated per-keypoint standard error (mm,
            :mod:`freipose.nn.uncertainty`), NaN where unknown; None: not estimated.
    """

    poses: np.ndarray
    confidence: np.ndarray
    points2d: np.ndarray
    confidence2d: np.ndarray
    boxes: np.ndarray
    center: np.ndarray
    uncertainty: np.ndarray | None = None

    def __post_init__(self) -> None:
        p = np.asarray(self.poses, np.float32)
        if p.ndim != 3 or p.shape[-1] != 3:
            raise ValueError(f"Estimate.poses must be (B, K, 3), got {p.shape}")
        b, k = p.shape[:2]
        p2 = np.asarray(self.points2d, np.float32)
        if p2.ndim != 4 or p2.shape[0] != b or p2.shape[2:] != (k, 2):
            raise ValueError(f"Estimate.points2d must be (B={b}, C, K={k}, 2), got {p2.shape}")
        c = p2.shape[1]
        shapes = {
            "confidence": (self.confidence, (b, k)),
            "confidence2d": (self.confidence2d, (b, c, k)),
            "boxes": (self.boxes, (b, c, 4)),
            "center": (self.center, (b, 3)),
        }
        for name, (arr, shape) in shapes.items():
            a = np.asarray(arr, np.float32)
            if a.shape != shape:
                raise ValueError(f"Estimate.{name} must have shape {shape}, got {a.shape}")
            object.__setattr__(self, name, a)
        if self.uncertainty is not None:
            u = np.asarray(self.uncertainty, np.float32)
            if u.shape != (b, k):
                raise ValueError(f"Estimate.uncertainty must have shape {(b, k)}, got {u.shape}")
            object.__setattr__(self, "uncertainty", u)
        conf = self.confidence
        conf = np.where(np.isfinite(conf), np.clip(conf, 0.0, 1.0), 0.0).astype(np.float32)
        missing = ~np.isfinite(p).all(-1)
        p = p.copy()
        p[missing] = np.nan
        conf[missing] = 0.0
        c2 = self.confidence2d
        c2 = np.where(np.isfinite(c2), np.clip(c2, 0.0, 1.0), 0.0).astype(np.float32)
        object.__setattr__(self, "poses", p)
        object.__setattr__(self, "confidence", conf)
        object.__setattr__(self, "points2d", p2)
        object.__setattr__(self, "confidence2d", c2)

    @property
    def batch_size(self) -> int:
        """B, the number of time steps."""
        return self.poses.shape[0]

    @classmethod
    def empty(cls, batch: int, cameras: int, keypoints: int) -> Estimate:
        """B time steps with nothing found: NaN everywhere, confidences 0."""
        nan = np.float32(np.nan)
        return cls(
            poses=np.full((batch, keypoints, 3), nan),
            confidence=np.zeros((batch, keypoints), np.float32),
            points2d=np.full((batch, cameras, keypoints, 2), nan),
            confidence2d=np.zeros((batch, cameras, keypoints), np.float32),
            boxes=np.full((batch, cameras, 4), nan),
            center=np.full((batch, 3), nan),
        )


@runtime_checkable
class PoseEstimator(Protocol):
    """Frames of synchronized cameras -> 3D poses.

    Attributes:
        keypoints: (K,) names of the predicted keypoints, in output order.
        provenance: facts to store in the output (e.g. ``model_sha256``); must not depend on
            the machine or time, so that resumed and sharded runs write equal files.
    """

    keypoints: tuple[str, ...]
    provenance: Mapping[str, Any]

    def __call__(self, images: Sequence[np.ndarray], rig: CameraRig) -> Estimate:
        """Predict B time steps.

        Args:
            images: one (B, H_c, W_c, 3) uint8 BGR array per camera of ``rig`` (C).
            rig: the cameras of the images (may be a subset of the session's cameras).

        Returns:
            An :class:`Estimate` with C cameras in ``rig`` order.
        """
        ...


def estimate_with_missing(
    estimator: PoseEstimator,
    images: Sequence[np.ndarray],
    valid: np.ndarray,
    rig: CameraRig,
    min_views: int = 2,
) -> tuple[Estimate, np.ndarray]:
    """Run ``estimator`` on a batch where some cameras' frames are missing.

    Time steps are grouped by which cameras have a frame; each group runs on the rig of its
    available cameras, and the results are scattered back to all C cameras (NaN for the
    missing ones). Time steps with fewer than ``min_views`` frames are not run.

    Args:
        estimator: the estimator to run.
        images: C arrays (B, H_c, W_c, 3).
        valid: (B, C) bool, the camera's frame was decoded.
        rig: the C cameras.
        min_views: fewest cameras with a frame for a time step to be run.

    Returns:
        (estimate over all C cameras, ran (B,) bool: the estimator ran for that time step)
    """
    valid = np.asarray(valid, bool)
    B, C = valid.shape
    K = len(estimator.keypoints)
    out = Estimate.empty(B, C, K)
    fields = {
        n: getattr(out, n).copy()
        for n in ("poses", "confidence", "points2d", "confidence2d", "boxes", "center")
    }
    fields["uncertainty"] = np.full((B, K), np.nan, np.float32)
    ran = np.zeros(B, bool)
    patterns = {tuple(row) for row in valid}
    for pat in sorted(patterns, reverse=True):
        cams = [c for c in range(C) if pat[c]]
        if len(cams) < min_views:
            continue
        rows = np.flatnonzero((valid == np.array(pat)).all(1))
        if len(cams) == C and len(rows) == B:
            sub_images = list(images)
            sub_rig = rig
        else:
            sub_images = [images[c][rows] for c in cams]
            sub_rig = rig.subset([rig.names[c] for c in cams])
        est = estimator(sub_images, sub_rig)
        if est.batch_size != len(rows) or est.points2d.shape[1] != len(cams):
            raise ValueError(
                f"estimator returned {est.batch_size} time steps x {est.points2d.shape[1]} "
                f"cameras for {len(rows)} x {len(cams)}"
            )
        if est.poses.shape[1] != K:
            raise ValueError(f"estimator returned {est.poses.shape[1]} keypoints, expected {K}")
        fields["poses"][rows] = est.poses
        fields["confidence"][rows] = est.confidence
        fields["center"][rows] = est.center
        if est.uncertainty is not None:
            fields["uncertainty"][rows] = est.uncertainty
        cam_idx = np.array(cams)
        for name in ("points2d", "confidence2d", "boxes"):
            arr = fields[name]
            arr[rows[:, None], cam_idx[None, :]] = getattr(est, name)
        ran[rows] = True
    return Estimate(**fields), ran
