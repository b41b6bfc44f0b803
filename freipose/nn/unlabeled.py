"""Unlabeled clips for training (the ``[unlabeled]`` table, :mod:`freipose.nn.config_unlabeled`).

Each step draws ``clips`` clips of ``clip_frames`` instants, ``clip_stride`` frames apart,
from the unlabeled sessions' videos (read with :class:`freipose.io.video.FrameSource`, as
the training dataset reads them) and prepares them as training samples are prepared
(:func:`freipose.nn.data.prepare_sample`: the same crops, augmentation and crop cameras),
around the cube centres of :func:`session_centers`. The middle instant of every clip is
prepared a second time with another augmentation and a random subset of its views, for the
equivariance loss. Like the labeled batches, the clips of a step are a function of
(seed, step) only, so a resumed run sees the clips the uninterrupted run would have.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from freipose.errors import FreiPoseError
from freipose.geometry.camera import CameraRig
from freipose.geometry.crops import label_centers
from freipose.io.calibration_world import rig_with_up
from freipose.io.labels import LabelSet
from freipose.io.poses import read_poses_h5
from freipose.io.session import discover_sessions
from freipose.io.video import FrameSource, MediaError
from freipose.nn.config import AugmentConfig, ModelConfig
from freipose.nn.config_unlabeled import UnlabeledConfig
from freipose.nn.data import collate_prepared, prepare_sample
from freipose.nn.types import Batch, PreparedSample, Sample

log = logging.getLogger(__name__)


class UnlabeledDataError(FreiPoseError):
    """The unlabeled sessions cannot be used (the message names the file and the fix)."""


@dataclass(frozen=True, eq=False)
class UnlabeledSession:
    """One unlabeled recording.

    Attributes:
        name: the session's name.
        rig: its C calibrated cameras (with the world's up where it is known).
        videos: camera name -> video file or image folder, in the rig's order.
        centers: (T, 3) cube centre of every frame (mm), NaN where the animal is unknown.
    """

    name: str
    rig: CameraRig
    videos: Mapping[str, Path]
    centers: np.ndarray

    @property
    def num_frames(self) -> int:
        """Frames of the session."""
        return len(self.centers)


def labels_center(labels: LabelSet, session: str) -> np.ndarray:
    """(3,) the median cube centre of the labels of ``session`` (of every label without any).

    Raises:
        UnlabeledDataError: the labels have no 3D point.
    """
    c = label_centers(labels.points3d)
    own = np.asarray(labels.session) == session
    pick = c[own] if np.isfinite(c[own]).all(-1).any() else c
    ok = np.isfinite(pick).all(-1)
    if not ok.any():
        raise UnlabeledDataError("unlabeled.centers = 'labels' needs labels with 3D points")
    return np.median(pick[ok], axis=0)


def poses_centers(path: Path, num_frames: int) -> np.ndarray:
    """(T, 3) per-frame cube centres from ``freipose predict``'s output, NaN where none.

    Raises:
        UnlabeledDataError: the file has no ``extra/center`` (not written by predict) or
            holds several animals.
    """
    data = read_poses_h5(path, require_up=False)
    center = data.extra.get("center")
    if center is None or np.asarray(center).ndim != 2:
        raise UnlabeledDataError(
            f"{path}: no per-frame cube centres (extra/center of one animal); give the output "
            "of `freipose predict` for this session, or set unlabeled.centers = 'labels'"
        )
    out = np.full((num_frames, 3), np.nan)
    fi = np.asarray(data.frame_index, np.int64)
    keep = (fi >= 0) & (fi < num_frames)
    out[fi[keep]] = np.asarray(center, np.float64)[keep]
    return out


def open_unlabeled(
    config: UnlabeledConfig, base: Path, labels: LabelSet, cameras: Sequence[str] | None = None
) -> list[UnlabeledSession]:
    """The unlabeled sessions of ``config`` with their cube centres.

    Args:
        config: the ``[unlabeled]`` table.
        base: the folder relative paths are relative to (the config file's).
        labels: the training labels (centres for ``centers = "labels"``, the world's up).
        cameras: use only these cameras (``[data] cameras``), else every calibrated one.

    Returns:
        One :class:`UnlabeledSession` per entry of ``config.sessions``.

    Raises:
        UnlabeledDataError: a session without usable frames or centres.
        SessionError, MediaError, InputFileError: a session folder that cannot be read
            (as for ``freipose predict``).
    """

    def rel(p: str) -> Path:
        q = Path(p).expanduser()
        return q if q.is_absolute() else base / q

    found = discover_sessions([rel(s) for s in config.sessions], cameras="calibration",
                              need_fps=False)  # fmt: skip
    out = []
    for i, s in enumerate(found):
        names = [c for c in s.rig.names if cameras is None or c in cameras]
        if len(names) < 2:
            raise UnlabeledDataError(
                f"unlabeled session {s.name!r} has {len(names)} usable camera(s) ({names}); "
                "the unlabeled losses need at least two views"
            )
        rig = rig_with_up(s.rig.subset(names), labels.points3d, f"session {s.name!r}'s grid")
        if config.centers == "poses":
            centers = poses_centers(rel(config.poses[i]), s.num_frames)
        else:
            centers = np.tile(labels_center(labels, s.name), (s.num_frames, 1))
        out.append(UnlabeledSession(s.name, rig, {c: s.videos[c] for c in names}, centers))
    return out


def clip_starts(sessions: Sequence[UnlabeledSession], frames: int, stride: int) -> np.ndarray:
    """(N, 2) ``(session, first frame)`` of every clip whose instants all have a centre.

    Raises:
        UnlabeledDataError: no such clip.
    """
    rows = []
    span = (frames - 1) * stride
    for si, s in enumerate(sessions):
        ok = np.isfinite(s.centers).all(-1)
        first = np.arange(max(s.num_frames - span, 0))
        good = np.ones(len(first), bool)
        for f in range(frames):
            good &= ok[first + f * stride]
        rows.extend((si, int(a)) for a in first[good])
    if not rows:
        raise UnlabeledDataError(
            f"no unlabeled clip of {frames} frames {stride} apart with a cube centre in "
            f"sessions {[s.name for s in sessions]}; lower unlabeled.clip_frames or check "
            "the centres (unlabeled.centers)"
        )
    return np.asarray(rows, np.int64)


@dataclass(frozen=True, eq=False)
class UnlabeledBatch:
    """The unlabeled instants of one step, collated.

    Instant ``c * F + f`` is frame ``f`` of clip ``c`` (F = ``clip_frames``); instant
    ``clips * F + c`` is the middle frame of clip ``c`` again, under another augmentation
    and with a random subset of its views (for the equivariance loss).

    Attributes:
        batch: the collated instants (no labels).
        clips: clips in the batch.
        clip_frames: instants per clip.
    """

    batch: Batch
    clips: int
    clip_frames: int

    @property
    def middle(self) -> int:
        """The frame of each clip that is prepared twice."""
        return self.clip_frames // 2


class UnlabeledClips:
    """Deterministic unlabeled clips per step (see the module docstring).

    Args:
        sessions: the unlabeled sessions.
        config: the ``[unlabeled]`` table.
        model: gives the crops and the cube.
        augment: the training augmentation (None: none; the equivariance copy still gets
            another subset of views).
        seed: the run's seed.
        clips: clips per step.
    """

    def __init__(
        self,
        sessions: Sequence[UnlabeledSession],
        config: UnlabeledConfig,
        model: ModelConfig,
        augment: AugmentConfig | None,
        seed: int,
        clips: int,
    ):
        self.sessions = list(sessions)
        self.config, self.model, self.augment = config, model, augment
        self.seed, self.clips = int(seed), int(clips)
        self.starts = clip_starts(self.sessions, config.clip_frames, config.clip_stride)
        self._sources: dict[tuple[int, str], FrameSource] = {}

    def _frame(self, si: int, camera: str, index: int) -> np.ndarray:
        key = (si, camera)
        src = self._sources.get(key)
        if src is None:
            src = FrameSource(self.sessions[si].videos[camera], cache_size=4 * self.clips)
            self._sources[key] = src
        try:
            return src.read(index)
        except (IndexError, MediaError) as exc:
            raise UnlabeledDataError(
                f"unlabeled session {self.sessions[si].name!r}, camera {camera!r}: {exc}"
            ) from exc

    def sample(self, si: int, frame: int) -> Sample:
        """The unlabeled instant ``frame`` of session ``si`` (rig and images, no labels)."""
        s = self.sessions[si]
        images = [self._frame(si, c, frame) for c in s.videos]
        return {"session": s.name, "frame_index": frame, "index": -1, "rig": s.rig,
                "camera_names": tuple(s.videos), "images": images}  # fmt: skip

    def _prepare(
        self, sample: Sample, center: np.ndarray, rng: np.random.Generator, subset: bool
    ) -> PreparedSample:
        """``sample`` cropped around ``center`` (jittered and augmented when augmenting)."""
        aug = self.augment if self.augment is not None and self.augment.enabled else None
        V = len(sample["images"])
        if subset and V > 2:
            n = int(rng.integers(2, V))  # 2 .. V-1 views
            aug = dataclasses.replace(aug or AugmentConfig(enabled=True, **_NO_AUG), max_views=n)
        if aug is not None and aug.center_jitter > 0:
            center = center + rng.normal(0.0, aug.center_jitter, size=3)
        return prepare_sample(sample, self.model, aug, rng, center=center)

    def batch(self, step: int) -> UnlabeledBatch:
        """The collated unlabeled instants of ``step`` (see :class:`UnlabeledBatch`)."""
        cfg = self.config
        rng = np.random.default_rng([self.seed, 104729, int(step)])
        pick = rng.choice(len(self.starts), size=self.clips, replace=len(self.starts) < self.clips)
        items: list[PreparedSample] = []
        middles: list[tuple[Sample, np.ndarray]] = []
        for c, row in enumerate(pick):
            si, first = (int(x) for x in self.starts[row])
            for f in range(cfg.clip_frames):
                fi = first + f * cfg.clip_stride
                smp = self.sample(si, fi)
                center = self.sessions[si].centers[fi]
                r = np.random.default_rng([self.seed, 104729, int(step), c, f])
                items.append(self._prepare(smp, center, r, subset=False))
                if f == cfg.clip_frames // 2:
                    middles.append((smp, center))
        for c, (smp, center) in enumerate(middles):
            r = np.random.default_rng([self.seed, 130363, int(step), c])
            items.append(self._prepare(smp, center, r, subset=True))
        return UnlabeledBatch(collate_prepared(items), self.clips, cfg.clip_frames)

    def close(self) -> None:
        """Release the open videos."""
        for src in self._sources.values():
            src.close()
        self._sources = {}


# an augmentation that only draws a subset of views (for runs without augmentation)
_NO_AUG = dict(
    center_jitter=0.0, grid_rotation=0.0, refine_jitter=0.0, rotation=0.0, zoom=(1.0, 1.0),
    shift=0.0, hue=0.0, brightness=0.0, contrast=0.0, blur_sigma=0.0, noise=0.0, salt_pepper=0.0,
)  # fmt: skip
