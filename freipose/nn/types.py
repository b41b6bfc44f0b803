"""The dicts that flow through the pose network, as ``TypedDict`` s with every key's shape.

Shapes: V views (cameras of a sample; in a batch the most views of its samples, padding
views masked), K keypoints, S crop size (pixels), B samples in a batch, G voxels per cube
edge. World coordinates are in mm; pixel coordinates follow the project convention (pixel
centres at integers).

* :class:`Sample`: one labeled time instant, as
  :class:`freipose.nn.dataset.MultiViewDataset` gives it; :class:`SampleSource`: anything
  that gives samples by index (the dataset, a list);
* :class:`PreparedSample`: its network input (:func:`freipose.nn.data.prepare_sample`);
* :class:`Batch`: prepared samples stacked into tensors
  (:func:`freipose.nn.data.collate_prepared`);
* :class:`NetworkOutput`: what the networks' ``forward`` returns;
* :class:`Prediction`: the batch predictions in world mm and full-image pixels
  (:func:`freipose.nn.inference.predict_prepared`).
"""

from __future__ import annotations

import sys
from typing import Protocol, TypedDict

import numpy as np
import torch

from freipose.geometry.camera import CameraRig

if sys.version_info >= (3, 11):
    from typing import NotRequired
else:  # pragma: no cover
    from typing_extensions import NotRequired


class Sample(TypedDict, total=False):
    """One multi-view time instant (numpy arrays).

    :class:`~freipose.nn.dataset.MultiViewDataset` gives every key; the network input
    (:func:`~freipose.nn.data.prepare_sample`) needs ``rig`` and reads the others when
    present (``images`` and the labels).

    Attributes:
        session: the session's name.
        frame_index: the frame of the session's videos.
        index: the sample's index in its dataset.
        rig: the V cameras, in view order (None for a 2D-only session without calibration).
        camera_names: (V,) names of the views (also for 2D-only sessions).
        images: V BGR uint8 (H, W, 3) full frames (``[]`` without images).
        points2d: (V, K, 2) float64 full-image pixels, NaN where unlabeled.
        visible2d: (V, K) bool, labeled and visible.
        points3d: (K, 3) float64 mm, NaN where unknown.
        mask3d: (K,) bool, finite ``points3d``.
        others3d: (M, K, 3) float64 mm, the other animals at this instant (labels with
            ``individual``, or a first inference pass); used by ``model.mask_others``.
        own3d: (K, 3) float64 mm, this animal's pose from a first inference pass (the
            body ``model.mask_others`` keeps; default ``points3d``).
    """

    session: str
    frame_index: int
    index: int
    rig: CameraRig | None
    camera_names: tuple[str, ...]
    images: list[np.ndarray]
    points2d: np.ndarray
    visible2d: np.ndarray
    points3d: np.ndarray
    mask3d: np.ndarray
    others3d: np.ndarray
    own3d: np.ndarray


class SampleSource(Protocol):
    """Samples by index: a :class:`~freipose.nn.dataset.MultiViewDataset` or a list."""

    def __len__(self) -> int: ...

    def __getitem__(self, index: int, /) -> Sample: ...


class PreparedSample(TypedDict):
    """The network input of one sample: view crops and their crop cameras (numpy arrays).

    Attributes:
        images: (V, 3, S, S) float32 crops, BGR / 255 - 0.5.
        K: (V, 3, 3) float64 affine crop intrinsics.
        R: (V, 3, 3) float64 rotations of the cameras.
        t: (V, 3) float64 translations (mm).
        dist: (V, 5) float64 OpenCV distortion coefficients.
        affine: (V, 3, 3) float64 map from full-image to crop pixels.
        view_valid: (V,) bool, the cube centre is in front of the camera.
        center: (3,) float64 cube centre (mm).
        grid_rotation: (3, 3) float64 orientation of the voxel grid axes in the world
            (identity unless augmenting).
        rig: the original V cameras.
        index: the sample's index in its dataset (-1 when unknown).
        points3d: (K, 3) float64 mm, NaN where unknown (labeled samples only).
        mask3d: (K,) bool, labeled 3D points (labeled samples only).
        points2d: (V, K, 2) float64 crop pixels (labeled samples only).
        visible2d: (V, K) bool, visible labels inside the crop of a valid view (labeled
            samples only).
        p0_jitter: (K, 3) float64 mm, training noise on P0 before the refinement
            (augmented labeled samples only).
    """

    images: np.ndarray
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    dist: np.ndarray
    affine: np.ndarray
    view_valid: np.ndarray
    center: np.ndarray
    grid_rotation: np.ndarray
    rig: CameraRig
    index: int
    points3d: NotRequired[np.ndarray]
    mask3d: NotRequired[np.ndarray]
    points2d: NotRequired[np.ndarray]
    visible2d: NotRequired[np.ndarray]
    p0_jitter: NotRequired[np.ndarray]


class Batch(TypedDict):
    """Prepared samples stacked into tensors, the view axis padded.

    Padding views have identity intrinsics and rotation, a camera 1 m in front of the cube
    and ``view_mask`` False.

    Attributes:
        images: (B, V, 3, S, S) float32 crops.
        K: (B, V, 3, 3) float32 affine crop intrinsics.
        R: (B, V, 3, 3) float32 rotations.
        t: (B, V, 3) float32 translations (mm).
        dist: (B, V, 5) float32 distortion coefficients.
        affine: (B, V, 3, 3) float32 full-image to crop pixels.
        center: (B, 3) float32 cube centres (mm).
        grid_rotation: (B, 3, 3) float32 voxel grid orientations.
        view_mask: (B, V) bool, real views with the centre in front of the camera.
        rigs: B original rigs.
        index: B dataset indices.
        points3d: (B, K, 3) float32 mm, 0 where unknown (labeled batches only).
        mask3d: (B, K) bool (labeled batches only).
        points2d: (B, V, K, 2) float32 crop pixels, 0 where unknown (labeled batches only).
        visible2d: (B, V, K) bool (labeled batches only).
        p0_jitter: (B, K, 3) float32 mm (when every sample has one).
    """

    images: torch.Tensor
    K: torch.Tensor
    R: torch.Tensor
    t: torch.Tensor
    dist: torch.Tensor
    affine: torch.Tensor
    center: torch.Tensor
    grid_rotation: torch.Tensor
    view_mask: torch.Tensor
    rigs: list[CameraRig]
    index: list[int]
    points3d: NotRequired[torch.Tensor]
    mask3d: NotRequired[torch.Tensor]
    points2d: NotRequired[torch.Tensor]
    visible2d: NotRequired[torch.Tensor]
    p0_jitter: NotRequired[torch.Tensor]


class NetworkOutput(TypedDict, total=False):
    """What the networks return.

    :class:`~freipose.nn.model.VoxelPoseNet` gives every key,
    :class:`~freipose.nn.model.BaselineNet` ``points2d``, ``confidence2d`` and ``map_logits``.

    Attributes:
        P0: (B, K, 3) float32 initial pose (mm), soft-argmax of the final score volume.
        P0_aux: list of (B, K, 3) deep-supervision decodings.
        confidence0: (B, K) peak mass of the score volumes.
        volume_probs: (B, K, G**3) softmax of the final score volume.
        P1: (B, K, 3) float32 refined pose (mm); P0 without the refinement head.
        points2d: (B, V, K, 2) refined crop pixels.
        confidence2d: (B, V, K) per-view confidences in [0, 1].
        confidence: (B, K) per-keypoint confidence in [0, 1].
        map_logits: (B, V, K, H, W) the 2D heads' map logits.
    """

    P0: torch.Tensor
    P0_aux: list[torch.Tensor]
    confidence0: torch.Tensor
    volume_probs: torch.Tensor
    P1: torch.Tensor
    points2d: torch.Tensor
    confidence2d: torch.Tensor
    confidence: torch.Tensor
    map_logits: torch.Tensor


class Prediction(TypedDict):
    """Predictions of a batch in world mm and full-image pixels (numpy arrays).

    Attributes:
        P0: (B, K, 3) float64 initial pose (mm); the baseline's triangulation.
        P1: (B, K, 3) float64 refined pose (mm); the baseline's triangulation.
        confidence: (B, K) in [0, 1].
        points2d: (B, V, K, 2) float64 full-image pixels, NaN on padding views.
        confidence2d: (B, V, K) in [0, 1], 0 on padding views.
    """

    P0: np.ndarray
    P1: np.ndarray
    confidence: np.ndarray
    points2d: np.ndarray
    confidence2d: np.ndarray
