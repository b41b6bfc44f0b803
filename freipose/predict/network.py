"""The real :class:`~freipose.predict.estimator.PoseEstimator`: box source + voxel network.

Per time step, the box source (trained detector, background subtraction or fixed boxes)
proposes boxes in every view; :func:`freipose.detect.detect_multiview_batch` turns them
into a consistent 3D centre; the voxel network (:func:`freipose.nn.inference.predict_batch`,
inference mode, on the backend of :mod:`freipose.nn.fast`, bfloat16 autocast on CUDA)
predicts the pose in a cube around it. A time step without a centre gives NaN poses with
confidence 0.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from freipose.geometry.camera import CameraRig
from freipose.geometry.crops import cube_crop_boxes
from freipose.io.session import Session
from freipose.io.video import frame_range
from freipose.predict.estimator import Estimate
from freipose.predict.run import (
    CHUNK_FRAMES,
    PredictError,
    PredictResult,
    output_path,
    predict_session,
)
from freipose.predict.writer import is_complete
from freipose.skeleton import Skeleton

if TYPE_CHECKING:
    from freipose.nn.config import InferenceOverrides

log = logging.getLogger(__name__)


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a file's bytes (hex).

    Args:
        path: the file.

    Returns:
        The hex digest.
    """
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def resolve_device(device: str) -> str:
    """``auto`` -> ``cuda`` when available, else ``cpu``; other values are checked.

    Args:
        device: ``cpu``, ``cuda``, ``cuda:N`` or ``auto``.

    Returns:
        The device to use.

    Raises:
        PredictError: an unknown device, or CUDA without a GPU.
    """
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise PredictError(f"--device {device}: CUDA is not available on this machine; use cpu")
    if device != "cpu" and not device.startswith("cuda"):
        raise PredictError(f"--device must be cpu, cuda, cuda:N or auto, got {device!r}")
    return device


@dataclass(frozen=True)
class DetectorSpec:
    """How to find the animal, plus the consistency settings.

    Attributes:
        method: ``detector`` (a trained detector, ``checkpoint``), ``bgsub`` (background
            subtraction), ``fixed`` (boxes from the ``fixed_boxes`` TOML file) or ``auto``
            (the first of these that finds the animal, fixed boxes derived from ``labels``
            last: :mod:`freipose.detect.auto`).
        checkpoint: the detector checkpoint (method ``detector``).
        fixed_boxes: the fixed boxes file (method ``fixed``).
        bg_samples: frames sampled for the background model (method ``bgsub``).
        min_views: fewest agreeing views for a 3D centre.
        labels: training labels for ``auto``'s fixed boxes (default: the model's).

    Raises:
        PredictError: an unknown method, or a method without its file.
    """

    method: str = "detector"
    checkpoint: Path | None = None
    fixed_boxes: Path | None = None
    bg_samples: int = 40
    min_views: int = 2
    labels: Path | None = None

    def __post_init__(self) -> None:
        if self.method not in ("detector", "bgsub", "fixed", "auto"):
            raise PredictError(
                f"unknown detection method {self.method!r}; use detector, bgsub, fixed or auto"
            )
        if self.method == "detector" and self.checkpoint is None:
            raise PredictError(
                "say how to find the animal: --detector CKPT (from `freipose train CONFIG "
                "--stage detector`), --method bgsub (static cameras, one animal) or "
                "--fixed-boxes FILE"
            )
        if self.method == "fixed" and self.fixed_boxes is None:
            raise PredictError("--method fixed needs --fixed-boxes FILE")

    def describe(self) -> dict[str, Any]:
        """The detection settings stored in the outputs' provenance (files by hash)."""
        out: dict[str, Any] = {"detection": self.method, "min_views": self.min_views}
        if self.method == "detector" and self.checkpoint is not None:
            out["detector_sha256"] = file_sha256(self.checkpoint)
            out["detector_file"] = Path(self.checkpoint).name
        if self.method == "fixed" and self.fixed_boxes is not None:
            out["fixed_boxes"] = Path(self.fixed_boxes).read_text()
        if self.method == "bgsub":
            out["bg_samples"] = self.bg_samples
        return out


class NetworkEstimator:
    """Detector + voxel network for one session (see the module docstring).

    Args:
        model: the network from :func:`freipose.nn.checkpoint.load_checkpoint`.
        config: its training config.
        skeleton: the keypoints it predicts.
        source: a box source (``propose(images, cameras) -> list[Candidates]``).
        refine: report the refined pose P1 (default) or the 3D network's P0.
        provenance: facts stored in the output (model hash, detection settings).
        min_views: fewest agreeing views for a 3D centre.
        uncertainty_scale: the scale of the per-keypoint uncertainty fitted on validation
            labels (:mod:`freipose.nn.uncertainty`); NaN: the uncertainty is not known.
    """

    def __init__(
        self,
        model: Any,
        config: Any,
        skeleton: Skeleton,
        source: Any,
        refine: bool = True,
        provenance: Mapping[str, Any] | None = None,
        min_views: int = 2,
        uncertainty_scale: float = float("nan"),
    ):
        from freipose.detect.multiview import ConsistencyConfig

        self.model = model
        self.config = config
        self.skeleton = skeleton
        self.source = source
        self.refine = refine
        self.cube_size = float(config.model.cube_size)
        self.consistency = ConsistencyConfig(cube_size=self.cube_size, min_views=min_views)
        self.keypoints = tuple(skeleton.keypoints)
        self.provenance = dict(provenance or {})
        self.uncertainty_scale = float(uncertainty_scale)

    def __call__(self, images: Sequence[np.ndarray], rig: CameraRig) -> Estimate:
        """Predict B time steps from one (B, H_c, W_c, 3) BGR array per camera of ``rig``."""
        import torch

        from freipose.detect.multiview import detect_multiview_batch

        C = len(rig)
        if len(images) != C:
            raise ValueError(f"got {len(images)} image batches for {C} cameras")
        B = images[0].shape[0]
        frames = [[images[c][b] for c in range(C)] for b in range(B)]
        with torch.inference_mode():
            dets = detect_multiview_batch(frames, rig, self.source, self.consistency)
        centers = np.stack([d.center for d in dets]).astype(np.float64)
        return self.predict_at(frames, rig, centers)

    def predict_at(
        self,
        frames: Sequence[Sequence[np.ndarray]],
        rig: CameraRig,
        centers: np.ndarray,
        animals: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> Estimate:
        """The network on cubes at given centres (the detection already done).

        Args:
            frames: per sample, one BGR image per camera of ``rig``.
            rig: the cameras (C).
            centers: (B, 3) world mm cube centres; a NaN row gives a sample not found.
            animals: ``(own, others)`` poses of a first pass for ``model.mask_others``
                (:func:`freipose.nn.inference.predict_batch`).

        Returns:
            The :class:`Estimate` of the B samples.
        """
        import torch

        from freipose.nn.inference import predict_batch
        from freipose.nn.uncertainty import raw_uncertainty

        C, B = len(rig), len(frames)
        with torch.inference_mode():
            out = predict_batch(self.model, frames, [rig] * B, centers, animals)
        poses = out["P1"] if self.refine else out["P0"]
        boxes = cube_crop_boxes(rig, centers, self.cube_size)  # (B, C, 4), NaN without centre
        raw = raw_uncertainty(out["P0"], out["P1"], out["points2d"], out["confidence2d"],
                              [rig] * B, self.config.model.voxel_size)  # fmt: skip
        return Estimate(
            poses=poses,
            confidence=out["confidence"],
            points2d=out["points2d"][:, :C],
            confidence2d=out["confidence2d"][:, :C],
            boxes=boxes,
            center=centers,
            uncertainty=self.uncertainty_scale * raw,
        )


def load_model(
    model_path: str | Path,
    device: str = "cpu",
    overrides: InferenceOverrides | None = None,
    backend: str = "eager",
) -> tuple[Any, Any, Skeleton, str]:
    """Load a pose checkpoint for prediction.

    Args:
        model_path: the checkpoint.
        device: where the network runs.
        overrides: inference-only ``[model]`` settings instead of the checkpoint's (None:
            its own).
        backend: how the network runs (:data:`freipose.nn.fast.BACKENDS`).

    Returns:
        ``(model, config, skeleton, sha256 of the file)``.

    Raises:
        InputFileError: no such file.
        CheckpointError: not a FreiPose pose checkpoint (e.g. a detector checkpoint), corrupt.
        PredictError: weights that do not fit the network (e.g. a hand-edited file), an
            unknown backend, ``bf16`` on a device without bfloat16 units.
    """
    from freipose.nn.checkpoint import load_checkpoint
    from freipose.nn.config import ConfigError
    from freipose.nn.fast import bf16_support, optimize, resolve_backend

    try:
        backend = resolve_backend(backend)
    except ValueError as exc:
        raise PredictError(f"--{exc}") from exc

    native, what = bf16_support(device) if backend == "bf16" else (True, "")
    if not native:
        raise PredictError(
            "--backend bf16 needs bfloat16 units (a CPU with AVX-512-BF16 or AMX, a GPU of "
            f"compute capability 8.0 or newer); {what} has none and would emulate bfloat16, "
            "many times slower than fp32: use --backend auto"
        )
    path = Path(model_path)
    try:
        model, config, skeleton = load_checkpoint(path, device, overrides=overrides)
    except (FileNotFoundError, ValueError, ConfigError):
        raise
    except Exception as exc:  # noqa: BLE001 - e.g. state-dict mismatches in a hand-edited file
        raise PredictError(f"{path}: cannot load the pose network ({exc})") from exc
    return optimize(model, backend), config, skeleton, file_sha256(path)


def check_keypoints(skeleton: Skeleton, expected: Skeleton | None, model_path: str | Path) -> None:
    """Check that the model predicts the keypoints of the expected skeleton.

    Args:
        skeleton: the model's skeleton.
        expected: the skeleton asked for (None: any).
        model_path: the checkpoint (for the message).

    Raises:
        PredictError: other keypoints or another order.
    """
    if expected is None:
        return
    if tuple(expected.keypoints) != tuple(skeleton.keypoints):
        raise PredictError(
            f"{model_path} was trained for keypoints {list(skeleton.keypoints)} (skeleton "
            f"{skeleton.name!r}) but {list(expected.keypoints)} (skeleton {expected.name!r}) "
            "were asked for; use a model trained for that skeleton or drop --skeleton"
        )


def make_box_source(
    spec: DetectorSpec, session: Session, frames: tuple[int, int], device: str
) -> Any:
    """The box source for one session (bgsub is fitted on the run's frames).

    Args:
        spec: how to find the animal.
        session: the session (its cameras and videos).
        frames: the run's frame range ``(start, stop)``.
        device: where the detector runs.

    Returns:
        An object with ``propose(images, cameras)``.

    Raises:
        PredictError: a detector checkpoint that cannot be used.
    """
    if spec.method == "auto":
        from freipose.detect.auto import auto_box_source

        return auto_box_source(
            session, frames, spec.checkpoint, spec.labels, spec.min_views, spec.bg_samples, device
        ).source
    if spec.method == "detector":
        from freipose.detect.detector import Detector

        if spec.checkpoint is None:
            raise PredictError("--method detector needs --detector CKPT")
        try:
            return Detector.load(spec.checkpoint, device)
        except FileNotFoundError:
            raise
        except Exception as exc:  # noqa: BLE001 - wrong checkpoint kind, state-dict mismatch
            raise PredictError(
                f"--detector {spec.checkpoint} is not a usable detector checkpoint (pass the file "
                f"written by `freipose train CONFIG --stage detector`): {exc}"
            ) from exc
    if spec.method == "fixed":
        from freipose.detect.fallback import FixedBoxes

        if spec.fixed_boxes is None:
            raise PredictError("--method fixed needs --fixed-boxes FILE")
        fb = FixedBoxes.from_toml(spec.fixed_boxes)
        fb.check_cameras(session.cameras)
        return fb
    from freipose.detect.fallback import BackgroundSubtractor
    from freipose.io.video import FrameSource

    sources = {c: FrameSource(p) for c, p in session.videos.items()}
    try:
        return BackgroundSubtractor.fit(
            sources, n_samples=spec.bg_samples, frames=range(frames[0], frames[1])
        )
    finally:
        for s in sources.values():
            s.close()


def network_provenance(
    net: Any, config: Any, sha: str, model_path: str | Path, spec: DetectorSpec, refine: bool
) -> tuple[dict[str, Any], float]:
    """The facts a prediction stores about its network and detection, and the uncertainty scale.

    Args:
        net: the loaded network (its backend is recorded).
        config: its training config.
        sha: the checkpoint's SHA-256.
        model_path: the checkpoint.
        spec: how the animal is found.
        refine: P1 (True) or P0 reported.

    Returns:
        ``(provenance, uncertainty scale)``; the scale is NaN when the checkpoint has none
        (fitted on validation labels after training), and in the provenance when it has.
    """
    from freipose.nn.checkpoint import validation_record
    from freipose.nn.config import inference_settings
    from freipose.nn.fast import backend_of

    provenance = {
        "model_sha256": sha,
        "model_file": Path(model_path).name,
        "refine": refine,
        "backend": backend_of(net),
        **spec.describe(),
        **inference_settings(config.model, refine),
    }
    scale = float(validation_record(model_path).get("uncertainty_scale", float("nan")))
    if np.isfinite(scale):
        provenance["uncertainty_scale"] = scale
    return provenance, scale


def predict_sessions(
    sessions: Sequence[Session],
    model_path: str | Path,
    spec: DetectorSpec,
    outdir: str | Path,
    *,
    frames: str | None = None,
    batch_size: int = 8,
    device: str = "auto",
    refine: bool = True,
    overrides: InferenceOverrides | None = None,
    backend: str = "auto",
    shard: tuple[int, int] | None = None,
    chunk_frames: int = CHUNK_FRAMES,
    overwrite: bool = False,
    expected_skeleton: Skeleton | None = None,
    progress: bool = True,
    report: Any = None,
    on_batch: Callable[[int], None] | None = None,
) -> list[Any]:
    """Predict validated sessions with a checkpoint (what ``freipose predict`` runs).

    Everything that can fail early is checked before the first frame: frame ranges, the
    model and its keypoints, the detector checkpoint or fixed boxes. Complete outputs are
    skipped unless ``overwrite``.

    Args:
        sessions: the sessions to predict.
        model_path: the pose checkpoint.
        spec: how to find the animal.
        outdir: the output folder.
        frames: the frame range ``START:STOP`` of every session (default: all).
        batch_size: time steps per network call.
        device: ``cpu``, ``cuda``, ``cuda:N`` or ``auto``.
        refine: report P1 (default) or P0.
        overrides: inference-only ``[model]`` settings instead of the checkpoint's (None:
            its own); the values that shape the reported pose are in the provenance.
        backend: how the network runs (:mod:`freipose.nn.fast`): ``auto``/``optimized``
            (the eager poses within fp32 rounding), ``eager`` (the reference) or ``bf16``;
            stored in the provenance.
        shard: ``(i, n)``: predict shard i of n.
        chunk_frames: rows per committed chunk; shard boundaries fall on whole chunks.
        overwrite: redo complete outputs.
        expected_skeleton: the keypoints the model must predict (None: any).
        progress: show progress bars.
        report: called with each session's result.
        on_batch: called after each batch with the rows written so far (of the session).

    Returns:
        One :class:`~freipose.predict.run.PredictResult` per session.
    """
    dev = resolve_device(device)
    bounds = {s.name: frame_range(frames, s.num_frames) for s in sessions}
    ranges = {name: (r.start, r.stop) for name, r in bounds.items()}
    net, config, skel, sha = load_model(model_path, dev, overrides, backend)
    check_keypoints(skel, expected_skeleton, model_path)
    if spec.method == "auto" and spec.labels is None and config.data.labels:
        spec = dataclasses.replace(spec, labels=Path(config.data.labels))  # the training labels
    shared = None
    if spec.method == "detector":
        shared = make_box_source(spec, sessions[0], ranges[sessions[0].name], dev)
    elif spec.method == "fixed":
        for s in sessions:  # every camera of every session must have a box
            shared = make_box_source(spec, s, ranges[s.name], dev)
    provenance, scale = network_provenance(net, config, sha, model_path, spec, refine)
    results = []
    for s in sessions:
        out = output_path(outdir, s.name, shard)
        if out.exists() and is_complete(out) and not overwrite:
            log.info("%s exists and is complete; skipping (use --overwrite to redo it)", out)
            res = PredictResult(path=out, skipped=True)
        else:
            source = shared or make_box_source(spec, s, ranges[s.name], dev)
            est = NetworkEstimator(
                net, config, skel, source, refine, provenance, spec.min_views, scale
            )
            res = predict_session(
                s, est, outdir, frames=ranges[s.name], batch_size=batch_size, shard=shard,
                overwrite=overwrite, skeleton=skel, chunk_frames=chunk_frames, progress=progress,
                on_batch=on_batch,
            )  # fmt: skip
        if report is not None:
            report(res)
        results.append(res)
    return results
