"""From multi-view samples (``freipose.nn.dataset.MultiViewDataset``) to network input.

For every view the voxel cube around the sample's centre (or its middle part,
``model.crop_fraction``) is projected into the full frame
(:func:`freipose.geometry.crops.cube_crop_boxes`), that square is cut out and resized to
the crop size, and the crop camera is derived exactly
(:func:`freipose.geometry.crops.crop_camera`). During training the centre is the mean of
the labeled 3D points plus Gaussian jitter, and each crop gets a random in-plane rotation,
zoom and shift that are folded into the crop camera (a general affine intrinsic matrix,
see :mod:`freipose.nn.geometry`), plus colour, blur and noise augmentation. Batches pad
the view axis; ``view_mask`` tells real views.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from freipose.errors import FreiPoseError
from freipose.geometry.camera import CameraRig
from freipose.geometry.crops import (
    crop_affine,
    cube_crop_boxes,
    label_centers,
    warp_to_crop,
)
from freipose.geometry.transforms import rodrigues
from freipose.io.calibration_world import stored_up_or_z
from freipose.nn.config import AugmentConfig, ModelConfig
from freipose.nn.instances import TRAIN_UNPAINTED, paint_other_animals
from freipose.nn.types import Batch, PreparedSample, Sample, SampleSource

BORDER = 128


class SampleError(FreiPoseError):
    """A sample cannot be turned into network input (the message says why)."""


def _aug_affine(rng: np.random.Generator, aug: AugmentConfig, size: int) -> np.ndarray:
    """Random rotation/zoom about the crop centre plus a shift (3x3, crop px -> crop px)."""
    c = (size - 1) / 2.0
    theta = math.radians(rng.uniform(-aug.rotation, aug.rotation))
    zoom = rng.uniform(aug.zoom[0], aug.zoom[1])
    dx, dy = rng.uniform(-aug.shift, aug.shift, size=2)
    cs, sn = math.cos(theta) * zoom, math.sin(theta) * zoom
    return np.array(
        [[cs, -sn, c - cs * c + sn * c + dx], [sn, cs, c - sn * c - cs * c + dy], [0, 0, 1]]
    )


def _color_augment(img: np.ndarray, rng: np.random.Generator, aug: AugmentConfig) -> np.ndarray:
    """Hue shift, brightness/contrast, Gaussian blur, noise and salt-and-pepper (BGR uint8)."""
    out = img
    if aug.hue > 0:
        hsv = cv2.cvtColor(out, cv2.COLOR_BGR2HSV)
        shift = int(round(rng.uniform(-aug.hue, aug.hue) / 2.0))  # OpenCV hue is 0..179
        hsv[..., 0] = ((hsv[..., 0].astype(np.int16) + shift) % 180).astype(np.uint8)
        out = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)
    f = out.astype(np.float32)
    if aug.brightness > 0 or aug.contrast > 0:
        gain = 1.0 + rng.uniform(-aug.contrast, aug.contrast)
        bias = 255.0 * rng.uniform(-aug.brightness, aug.brightness)
        f = (f - 128.0) * gain + 128.0 + bias
    if aug.blur_sigma > 0:
        sigma = rng.uniform(0.0, aug.blur_sigma)
        if sigma > 0.05:
            f = cv2.GaussianBlur(f, (7, 7), sigma)
    if aug.noise > 0:
        f = f + rng.normal(0.0, 255.0 * aug.noise * rng.uniform(), size=f.shape).astype(np.float32)
    if aug.salt_pepper > 0:
        u = rng.uniform(size=f.shape[:2])
        f[u < aug.salt_pepper] = 0.0
        f[u > 1 - aug.salt_pepper] = 255.0
    return np.clip(f, 0, 255).astype(np.uint8)


def _sample_rig(sample: Sample) -> CameraRig:
    """The sample's cameras.

    Raises:
        SampleError: the sample has no calibration.
    """
    rig = sample.get("rig")
    if rig is None:
        raise SampleError(
            f"sample {sample.get('index')} (session {sample.get('session')!r}) has no calibration; "
            "the pose network needs calibrated cameras"
        )
    return rig


def _view_subset(sample: Sample, rng: np.random.Generator, n: int) -> Sample:
    """The sample with ``n`` of its V views, drawn at random (kept in view order)."""
    rig = _sample_rig(sample)
    keep = np.sort(rng.choice(len(rig), size=n, replace=False))
    out: Sample = {**sample, "rig": rig.subset([int(v) for v in keep])}
    if sample.get("images"):
        out["images"] = [sample["images"][int(v)] for v in keep]
    if sample.get("camera_names"):
        out["camera_names"] = tuple(sample["camera_names"][int(v)] for v in keep)
    for key in ("points2d", "visible2d"):
        if sample.get(key) is not None:
            out[key] = np.asarray(sample[key])[keep]  # type: ignore[literal-required]
    return out


@dataclass(frozen=True)
class Augmentation:
    """The training augmentation of one sample.

    Attributes:
        config: what to augment and by how much.
        rng: the random generator every augmentation draws from.
    """

    config: AugmentConfig
    rng: np.random.Generator


def _cube_center(sample: Sample, aug: Augmentation | None, center: np.ndarray | None) -> np.ndarray:
    """The (3,) cube centre: ``center``, or the labels' mean plus jitter when augmenting.

    Raises:
        SampleError: no ``center`` and no 3D label.
    """
    if center is None:
        p3 = sample.get("points3d")
        if p3 is None:
            raise SampleError("prepare_sample needs a centre or 3D labels")
        center = label_centers(p3, sample.get("mask3d"))
        if not np.all(np.isfinite(center)):
            raise SampleError(
                f"sample {sample.get('index')} (session {sample.get('session')!r}, frame "
                f"{sample.get('frame_index')}) has no 3D label to centre the voxel cube on"
            )
        if aug is not None and aug.config.center_jitter > 0:
            center = center + aug.rng.normal(0.0, aug.config.center_jitter, size=3)
    return np.asarray(center, dtype=np.float64).reshape(3)


def _grid_rotation(aug: Augmentation | None, rig: CameraRig) -> np.ndarray:
    """(3, 3) voxel grid orientation: a random turn about the world's up when augmenting.

    The up is the one the rig's calibration stores (:mod:`freipose.io.calibration_world`;
    the training dataset resolves it per session), else world z.
    """
    if aug is None or aug.config.grid_rotation <= 0:
        return np.eye(3)
    a = math.radians(aug.rng.uniform(-aug.config.grid_rotation, aug.config.grid_rotation))
    return rodrigues(a * stored_up_or_z(rig))


@dataclass(frozen=True)
class ViewCrops:
    """The crops of the V views of a sample.

    Attributes:
        images: (V, 3, S, S) float32 crops, BGR / 255 - 0.5 (0 for views without a crop).
        K: (V, 3, 3) affine crop intrinsics.
        affine: (V, 3, 3) full-image to crop pixels.
        valid: (V,) bool, the cube centre is in front of the camera.
    """

    images: np.ndarray
    K: np.ndarray
    affine: np.ndarray
    valid: np.ndarray


def _crop_image(
    img: np.ndarray,
    A: np.ndarray,
    size: int,
    aug: Augmentation | None,
) -> np.ndarray:
    """Warp a full frame into its (3, S, S) float32 crop (BGR / 255 - 0.5), augmented.

    A crop that shrinks the frame by more than 2x is antialiased (:func:`warp_to_crop`).
    """
    crop = warp_to_crop(img, A, size, (BORDER, BORDER, BORDER))
    if crop.ndim == 2:
        crop = np.repeat(crop[..., None], 3, axis=-1)
    if aug is not None:
        crop = _color_augment(crop, aug.rng, aug.config)
    return crop.transpose(2, 0, 1).astype(np.float32) / 255.0 - 0.5


def _crop_views(
    rig: CameraRig,
    images: list[np.ndarray],
    center: np.ndarray,
    model: ModelConfig,
    aug: Augmentation | None,
) -> ViewCrops:
    """Cut every view's crop around the cube and derive its crop camera.

    The random generator is drawn view by view (the view's geometric augmentation, then
    its colour augmentation), so a sample is a function of the generator's seed.

    Raises:
        SampleError: an image's size differs from its camera's.
    """
    S = model.crop_size
    V = len(rig)
    boxes = cube_crop_boxes(rig, center, model.crop_cube)  # (V, 4)
    out_img = np.zeros((V, 3, S, S), np.float32)
    Ks = np.tile(np.eye(3), (V, 1, 1))
    affines = np.tile(np.eye(3), (V, 1, 1))
    valid = np.zeros(V, bool)
    for v, cam in enumerate(rig):
        box = boxes[v]
        if not np.all(np.isfinite(box)) or box[2] - box[0] <= 0:
            continue  # centre behind this camera
        valid[v] = True
        T = _aug_affine(aug.rng, aug.config, S) if aug is not None else np.eye(3)
        A = T @ crop_affine(box, S)
        Ks[v] = A @ cam.K  # the crop camera's intrinsics (crop_camera) after T
        affines[v] = A
        if images:
            img = images[v]
            if img.shape[1] != cam.width or img.shape[0] != cam.height:
                raise SampleError(
                    f"camera {cam.name!r}: image is {img.shape[1]}x{img.shape[0]} but the "
                    f"calibration says {cam.width}x{cam.height}"
                )
            out_img[v] = _crop_image(img, A, S, aug)
    return ViewCrops(out_img, Ks, affines, valid)


@dataclass(frozen=True)
class CropLabels:
    """The labels of a sample in its crops.

    Attributes:
        points3d: (K, 3) mm, NaN where unknown.
        mask3d: (K,) bool, labeled 3D points.
        points2d: (V, K, 2) crop pixels.
        visible2d: (V, K) bool, visible labels inside the crop of a valid view.
    """

    points3d: np.ndarray
    mask3d: np.ndarray
    points2d: np.ndarray
    visible2d: np.ndarray


def _crop_labels(sample: Sample, crops: ViewCrops, size: int) -> CropLabels:
    """The sample's 3D labels and its 2D labels mapped into the crops."""
    p3 = np.asarray(sample["points3d"], np.float64)
    nk = p3.shape[0]
    V = len(crops.valid)
    m3 = np.isfinite(p3).all(-1)
    if sample.get("mask3d") is not None:
        m3 &= np.asarray(sample["mask3d"], bool)
    p2 = np.asarray(sample.get("points2d", np.full((V, nk, 2), np.nan)), np.float64)
    given = sample.get("visible2d")
    finite2 = np.isfinite(p2).all(-1)
    vis = finite2 if given is None else np.asarray(given, bool) & finite2
    hom = np.concatenate([p2, np.ones(p2.shape[:-1] + (1,))], -1)
    p2c = np.einsum("vij,vkj->vki", crops.affine, hom)[..., :2]
    inside = (p2c >= -0.5).all(-1) & (p2c <= size - 0.5).all(-1)
    return CropLabels(p3, m3, p2c, vis & inside & crops.valid[:, None])


def _other_animals_painted(
    sample: Sample,
    rig: CameraRig,
    images: list[np.ndarray],
    model: ModelConfig,
    aug: Augmentation | None,
) -> list[np.ndarray]:
    """The views with the other animals painted out (``model.mask_others``).

    The other animals are ``others3d``, this animal ``own3d`` (else its labels). When
    augmenting, a share of the samples stays unpainted and the poses get the P0 jitter
    (``augment.refine_jitter``), as the first inference pass's poses would be off.
    """
    others = sample.get("others3d")
    if others is None or np.size(others) == 0:
        return images
    own = sample.get("own3d", sample.get("points3d"))
    others = np.asarray(others, np.float64)
    if aug is not None:
        if aug.rng.random() < TRAIN_UNPAINTED:
            return images
        sd = aug.config.refine_jitter
        others = others + aug.rng.normal(0.0, sd, size=others.shape)
        if own is not None:
            own = np.asarray(own, np.float64) + aug.rng.normal(0.0, sd, size=np.shape(own))
    return paint_other_animals(images, rig, own, others, model.mask_radius)


def prepare_sample(
    sample: Sample,
    model: ModelConfig,
    augment: AugmentConfig | None = None,
    rng: np.random.Generator | None = None,
    center: np.ndarray | None = None,
) -> PreparedSample:
    """Crop one multi-view sample around its centre.

    The stages: the cube centre (:func:`_cube_center`), the voxel grid's orientation
    (:func:`_grid_rotation`), the view crops and crop cameras (:func:`_crop_views`) and the
    labels in the crops (:func:`_crop_labels`); with augmentation they draw from ``rng`` in
    that order, then the P0 jitter (with ``model.mask_others`` and other animals in the
    sample, the painting draws first: :func:`_other_animals_painted`).

    Args:
        sample: a ``MultiViewDataset`` sample (``rig``, ``images``, optional labels).
        model: gives the crop size and the cube size.
        augment: training augmentation (None or ``enabled=False``: none).
        rng: random generator for the augmentation (required with augmentation).
        center: (3,) cube centre in mm; default the mean of the labeled 3D points
            (plus jitter when augmenting).

    Returns:
        The :class:`~freipose.nn.types.PreparedSample` (labels only for a sample with
        ``points3d``; ``p0_jitter`` only when augmenting with ``refine_jitter``).

    Raises:
        SampleError: no rig, no centre, or images that do not match the cameras.
        ValueError: augmentation without ``rng``.
    """
    rig = _sample_rig(sample)
    aug = None
    if augment is not None and augment.enabled:
        if rng is None:
            raise ValueError("prepare_sample: augmentation needs an rng")
        aug = Augmentation(augment, rng)
        if 0 < augment.max_views < len(rig):
            sample = _view_subset(sample, rng, augment.max_views)
            rig = _sample_rig(sample)
    center = _cube_center(sample, aug, center)
    grid_rot = _grid_rotation(aug, rig)
    images = sample.get("images") or []
    if images and len(images) != len(rig):
        raise SampleError(f"sample has {len(images)} images for {len(rig)} cameras")
    if model.mask_others and images:
        images = _other_animals_painted(sample, rig, images, model, aug)
    crops = _crop_views(rig, images, center, model, aug)
    res: PreparedSample = {
        "images": crops.images,
        "K": crops.K,
        "R": np.asarray(rig.R, np.float64),
        "t": np.asarray(rig.t, np.float64),
        "dist": np.asarray(rig.dist, np.float64),
        "affine": crops.affine,
        "view_valid": crops.valid,
        "center": center,
        "grid_rotation": grid_rot,
        "rig": rig,
        "index": int(sample.get("index", -1)),
    }
    if sample.get("points3d") is not None:
        lab = _crop_labels(sample, crops, model.crop_size)
        res["points3d"] = lab.points3d
        res["mask3d"] = lab.mask3d
        res["points2d"] = lab.points2d
        res["visible2d"] = lab.visible2d
        if aug is not None and aug.config.refine_jitter > 0:
            nk = lab.points3d.shape[0]
            res["p0_jitter"] = aug.rng.normal(0.0, aug.config.refine_jitter, size=(nk, 3))
    return res


def collate_prepared(items: list[PreparedSample]) -> Batch:
    """Stack prepared samples into tensors, padding the view axis.

    Args:
        items: B prepared samples (:func:`prepare_sample`); the labels are stacked when
            every sample has them, ``p0_jitter`` when every sample has one.

    Returns:
        The :class:`~freipose.nn.types.Batch` (padding views: identity intrinsics, a camera
        1 m in front of the cube, ``view_mask`` False).
    """
    B = len(items)
    V = max(len(it["view_valid"]) for it in items)
    S = items[0]["images"].shape[-1]
    out: Batch = {
        "images": torch.zeros(B, V, 3, S, S),
        "K": torch.eye(3).repeat(B, V, 1, 1),
        "R": torch.eye(3).repeat(B, V, 1, 1),
        "t": torch.zeros(B, V, 3),
        "dist": torch.zeros(B, V, 5),
        "affine": torch.eye(3).repeat(B, V, 1, 1),
        "center": torch.zeros(B, 3),
        "grid_rotation": torch.eye(3).repeat(B, 1, 1),
        "view_mask": torch.zeros(B, V, dtype=torch.bool),
        "rigs": [it["rig"] for it in items],
        "index": [it["index"] for it in items],
    }
    out["t"][..., 2] = 1000.0
    labeled = all("points3d" in it for it in items)
    if labeled:
        nk = items[0]["points3d"].shape[0]
        out["points3d"] = torch.zeros(B, nk, 3)
        out["mask3d"] = torch.zeros(B, nk, dtype=torch.bool)
        out["points2d"] = torch.zeros(B, V, nk, 2)
        out["visible2d"] = torch.zeros(B, V, nk, dtype=torch.bool)
    for b, it in enumerate(items):
        n = len(it["view_valid"])
        out["images"][b, :n] = torch.from_numpy(it["images"])
        for key in ("K", "R", "t", "dist", "affine"):
            out[key][b, :n] = torch.from_numpy(np.asarray(it[key], np.float32))
        out["center"][b] = torch.from_numpy(np.asarray(it["center"], np.float32))
        if "grid_rotation" in it:
            out["grid_rotation"][b] = torch.from_numpy(np.asarray(it["grid_rotation"], np.float32))
        out["view_mask"][b, :n] = torch.from_numpy(it["view_valid"])
        if labeled:
            out["points3d"][b] = torch.from_numpy(np.nan_to_num(it["points3d"]).astype(np.float32))
            out["mask3d"][b] = torch.from_numpy(it["mask3d"])
            out["points2d"][b, :n] = torch.from_numpy(
                np.nan_to_num(it["points2d"]).astype(np.float32)
            )
            out["visible2d"][b, :n] = torch.from_numpy(it["visible2d"])
    if all("p0_jitter" in it for it in items):
        out["p0_jitter"] = torch.from_numpy(
            np.stack([it["p0_jitter"] for it in items]).astype(np.float32)
        )
    return out


TENSOR_KEYS = (
    "images",
    "K",
    "R",
    "t",
    "dist",
    "affine",
    "center",
    "grid_rotation",
    "view_mask",
    "points3d",
    "mask3d",
    "points2d",
    "visible2d",
    "p0_jitter",
)


def to_device(batch: Batch, device: torch.device | str) -> Batch:
    """Move the tensors of a collated batch to ``device``.

    Args:
        batch: from :func:`collate_prepared`.
        device: the target device.

    Returns:
        The batch with its tensors on ``device`` (``rigs`` and ``index`` as they are).
    """
    return {
        k: (v.to(device, non_blocking=True) if k in TENSOR_KEYS else v) for k, v in batch.items()
    }


class TrainSamples(torch.utils.data.Dataset):
    """Prepared training samples addressed by ``(index, step)``.

    The augmentation randomness comes from ``numpy.random.default_rng([seed, step, index])``,
    so a sample is the same whichever process or worker makes it, and a resumed run sees
    exactly the data the uninterrupted run would have seen.
    """

    def __init__(
        self,
        source: SampleSource,
        model: ModelConfig,
        augment: AugmentConfig | None,
        seed: int,
    ):
        self.source = source
        self.model = model
        self.augment = augment
        self.seed = int(seed)

    def __len__(self) -> int:
        return len(self.source)

    def __getitem__(self, key: tuple[int, int]) -> PreparedSample:
        index, step = key
        rng = np.random.default_rng([self.seed, int(step), int(index)])
        return prepare_sample(self.source[int(index)], self.model, self.augment, rng)


class StepBatchSampler(torch.utils.data.Sampler):
    """Batches of ``(index, step)`` keys for steps ``start .. steps-1``.

    The global batch of step ``s`` is the next ``batch_size`` entries of a sequence of
    per-epoch permutations of ``indices`` (seeded by ``seed`` and the epoch); process
    ``rank`` of ``world`` takes its contiguous share. Deterministic in (seed, step).
    """

    def __init__(
        self,
        indices: Sequence[int] | np.ndarray,
        batch_size: int,
        steps: int,
        seed: int,
        start: int = 0,
        rank: int = 0,
        world: int = 1,
    ):
        if not len(indices):
            raise SampleError("no training samples (no labeled time instant with 3D labels)")
        if batch_size % world:
            raise SampleError(
                f"schedule.batch_size ({batch_size}) must be divisible by the number of "
                f"processes ({world})"
            )
        self.indices = np.asarray(indices, dtype=np.int64)
        self.batch_size, self.steps, self.seed = batch_size, steps, seed
        self.start, self.rank, self.world = start, rank, world

    def __len__(self) -> int:
        return max(self.steps - self.start, 0)

    def global_batch(self, step: int) -> np.ndarray:
        """The dataset indices of the global batch of ``step``."""
        n = len(self.indices)
        pos = np.arange(step * self.batch_size, (step + 1) * self.batch_size)
        epochs = pos // n
        out = np.empty(len(pos), np.int64)
        for e in np.unique(epochs):
            perm = np.random.default_rng([self.seed, 7919, int(e)]).permutation(n)
            sel = epochs == e
            out[sel] = self.indices[perm[pos[sel] % n]]
        return out

    def __iter__(self) -> Iterator[list[tuple[int, int]]]:
        local = self.batch_size // self.world
        for step in range(self.start, self.steps):
            g = self.global_batch(step)[self.rank * local : (self.rank + 1) * local]
            yield [(int(i), step) for i in g]
