"""The persistent part of a network's error, from its held-out validation, for the smoother.

The network's error on one recording is mostly a slowly varying offset per keypoint (it
changes over seconds, not frames), which a smoother fitted on the recording alone cannot
see: its posterior standard deviation describes only the frame-to-frame noise. The error
of the same network on held-out labeled instants (labels it was not trained on, with 3D
points, as ``freipose eval`` predicts them: the cube on the labels' centre) measures that
offset. :class:`HeldOutError` holds its root mean square per keypoint and axis, which
:func:`freipose.predict.smooth.smooth_poses` adds in quadrature to the smoother's
standard deviation, so the reported band covers the network's error without truth on the
recording.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from freipose.errors import FreiPoseError

if TYPE_CHECKING:
    from freipose.nn.config import InferenceOverrides

MIN_INSTANTS = 5


class ValidationLabelsError(FreiPoseError):
    """The validation error cannot be measured or does not fit the poses."""


@dataclass(frozen=True)
class HeldOutError:
    """Root mean square error per keypoint and axis on held-out labeled instants.

    Attributes:
        keypoints: (K,) keypoint names.
        rms: (K, 3) root mean square error in mm per world axis.
        count: (K,) labeled instants each keypoint's error comes from.
        source: what was measured (model and labels files, which prediction).
    """

    keypoints: tuple[str, ...]
    rms: np.ndarray
    count: np.ndarray
    source: str

    def for_keypoints(self, keypoints: Sequence[str]) -> np.ndarray:
        """(K', 3) rms in the order of ``keypoints``.

        Raises:
            ValidationLabelsError: a keypoint has no validation error.
        """
        missing = [k for k in keypoints if k not in self.keypoints]
        if missing:
            raise ValidationLabelsError(
                f"the validation labels have no keypoints {missing} of the poses (they have "
                f"{list(self.keypoints)}); pass --validation labels of the same skeleton"
            )
        return self.rms[[self.keypoints.index(k) for k in keypoints]]

    def as_dict(self) -> dict[str, Any]:
        """The values per keypoint name, for provenance."""
        return {
            "source": self.source,
            "rms_mm": {
                k: [float(v) for v in r] for k, r in zip(self.keypoints, self.rms, strict=True)
            },
            "instants": {k: int(n) for k, n in zip(self.keypoints, self.count, strict=True)},
        }


def validation_error(
    pred: np.ndarray, truth: np.ndarray, keypoints: Sequence[str], source: str = ""
) -> HeldOutError:
    """The per-keypoint, per-axis RMS error of predictions against their labels.

    Args:
        pred: (N, K, 3) predicted points in mm.
        truth: (N, K, 3) labeled points in mm, NaN where unlabeled.
        keypoints: (K,) names.
        source: what was measured.

    Raises:
        ValidationLabelsError: a keypoint has fewer than :data:`MIN_INSTANTS` labels.
    """
    err = np.asarray(pred, np.float64) - np.asarray(truth, np.float64)
    ok = np.asarray(np.isfinite(err).all(axis=-1))
    count = ok.sum(axis=0)
    few = [k for k, n in zip(keypoints, count, strict=True) if n < MIN_INSTANTS]
    if few:
        raise ValidationLabelsError(
            f"keypoints {few} have fewer than {MIN_INSTANTS} labeled held-out instants; "
            "pass --validation labels with more 3D-labeled instants"
        )
    sq = np.where(ok[..., None], err, 0.0) ** 2
    rms = np.sqrt(sq.sum(axis=0) / count[:, None])
    return HeldOutError(tuple(keypoints), rms, count, source)


def model_validation_error(
    model_path: str | Path,
    labels_path: str | Path,
    refine: bool = True,
    device: str = "cpu",
    batch_size: int = 4,
    max_instants: int | None = None,
    overrides: InferenceOverrides | None = None,
) -> HeldOutError:
    """Predict the 3D-labeled instants of ``labels_path`` and measure the error.

    The cube sits on the labels' centre, as in ``freipose eval``.

    Args:
        model_path: the pose checkpoint that predicted the poses.
        labels_path: held-out labels (not trained on) with 3D points.
        refine: measure the refined pose P1 (what ``predict`` reports by default) or P0.
        device: torch device.
        batch_size: instants per forward pass.
        max_instants: predict at most this many instants, evenly spread (None: all).
        overrides: the inference-only settings the poses were predicted with (None: the
            checkpoint's; :func:`predicted_by`).

    Raises:
        ValidationLabelsError: the labels have no usable instant, or too few per keypoint.
        InputFileError: a file cannot be read.
    """
    from freipose.io.labels import read_labels_h5
    from freipose.nn.checkpoint import load_checkpoint
    from freipose.nn.dataset import MultiViewDataset
    from freipose.nn.evaluate import predict_dataset, usable_indices

    labels_path = Path(labels_path)
    labels = read_labels_h5(labels_path)
    model, _, skeleton = load_checkpoint(model_path, device, overrides=overrides)
    if tuple(labels.keypoints) != tuple(skeleton.keypoints):
        raise ValidationLabelsError(
            f"--validation {labels_path} has keypoints {list(labels.keypoints)}, the model "
            f"{list(skeleton.keypoints)}; pass labels of the model's skeleton"
        )
    source = MultiViewDataset(labels, root=labels_path.parent)
    idx = usable_indices(source)
    if max_instants is not None and len(idx) > max_instants:
        idx = idx[np.linspace(0, len(idx) - 1, max_instants).round().astype(int)]
    pred = predict_dataset(model, source, idx, batch_size=batch_size)
    if not len(pred["index"]):
        raise ValidationLabelsError(
            f"--validation {labels_path} has no instant with 3D labels and a calibration; "
            "pass held-out labels with 3D points"
        )
    which = "P1" if refine else "P0"
    what = f"{which} of {Path(model_path).name} on {len(pred['index'])} instants of {labels_path}"
    return validation_error(pred[which], pred["gt"], skeleton.keypoints, what)


@dataclass(frozen=True)
class PredictedBy:
    """What the poses files' provenance says of how they were predicted.

    Attributes:
        refine: whether they report the refined pose P1 (else P0).
        overrides: the inference-only settings they record (None where not recorded: the
            checkpoint's own).
    """

    refine: bool
    overrides: InferenceOverrides


# the inference-only settings a poses file records: their option and their type
_SETTINGS = {"fusion_reject": ("--fusion-reject", float), "map_window": ("--map-window", int)}


def predicted_by(poses: Sequence[Path], model: Path) -> PredictedBy:
    """Check that the poses files were predicted alike by ``model``; say how.

    Args:
        poses: the poses files.
        model: the checkpoint that should have predicted them.

    Raises:
        ValidationLabelsError: a file names another model (by hash), or the files differ in
            whether they report P1 or in their ``--fusion-reject`` or ``--map-window``.
    """
    from freipose.io.poses import read_poses_h5
    from freipose.nn.config import InferenceOverrides
    from freipose.predict.network import file_sha256

    digest = file_sha256(model)
    refine: set[bool] = set()
    values: dict[str, set[Any]] = {name: set() for name in _SETTINGS}
    for p in poses:
        prov = read_poses_h5(p).provenance
        theirs = prov.get("model_sha256")
        if theirs is not None and theirs != digest:
            raise ValidationLabelsError(
                f"{p} was predicted by {prov.get('model_file', 'another model')} "
                f"(sha256 {str(theirs)[:12]}), not by --model {model} (sha256 {digest[:12]}); "
                "pass the checkpoint that predicted the poses"
            )
        refine.add(bool(prov.get("refine", True)))
        for name, seen in values.items():
            seen.add(prov.get(name))
    if len(refine) > 1:
        raise ValidationLabelsError(
            "some poses files report the refined pose P1 and some P0; smooth them separately"
        )
    for name, seen in values.items():
        if len(seen) > 1:
            raise ValidationLabelsError(
                f"the poses files were predicted with different {_SETTINGS[name][0]} "
                f"values {sorted(map(str, seen))}; smooth them separately"
            )
    recorded = {name: seen.pop() if seen else None for name, seen in values.items()}
    overrides = {
        name: None if value is None else _SETTINGS[name][1](value)
        for name, value in recorded.items()
    }
    return PredictedBy(refine.pop() if refine else True, InferenceOverrides(**overrides))


def fit_error_floor(
    mean: np.ndarray, std: np.ndarray, truth: np.ndarray, target: float = 0.954
) -> np.ndarray:
    """Per-keypoint error floor ``b`` (mm) so that ``sqrt(std^2 + b^2)`` covers ``target``.

    The smoother's standard deviation describes the frame-to-frame noise of the
    predictions; an error that persists over many frames (a network bias) is invisible in
    one recording. Fitted on a recording with truth, the floor adds it back: the smallest
    ``b`` with which a share ``target`` of the axes lie within 2 sigma.

    Args:
        mean: (T, K, 3) smoothed positions in mm.
        std: (T, K, 3) their standard deviations in mm.
        truth: (T, K, 3) true positions in mm (NaN where unknown).
        target: the 2-sigma coverage to reach (0.954: a Gaussian's).

    Returns:
        (K,) floor in mm (0 where the smoother's own std already reaches ``target``).
    """
    err = np.abs(np.asarray(mean, np.float64) - truth)
    var = np.asarray(std, np.float64) ** 2
    floor = np.zeros(err.shape[1])
    for k in range(err.shape[1]):
        ok = np.isfinite(err[:, k])
        e, v = err[:, k][ok], var[:, k][ok]
        if not e.size:
            continue
        lo, hi = 0.0, float(e.max()) / 2 + 1e-9
        for _ in range(50):
            b = (lo + hi) / 2
            lo, hi = (b, hi) if (e <= 2 * np.sqrt(v + b * b)).mean() < target else (lo, b)
        floor[k] = hi if (e <= 2 * np.sqrt(v)).mean() < target else 0.0
    return floor
