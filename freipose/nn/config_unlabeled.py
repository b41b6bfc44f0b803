"""The ``[unlabeled]`` table of a training config: training on the lab's unlabeled video.

Short clips of consecutive frames are drawn from the listed sessions (folders with videos
and ``calibration.toml``, as ``freipose predict`` takes them) and added to every step; the
losses of :mod:`freipose.nn.unlabeled_losses` need no labels: the views of an instant must
agree (``multiview``), P0 must agree with P1 (``p0p1``), a clip must move smoothly
(``temporal``), the same instant under another augmentation and another subset of views
must give the same 3D pose (``equivariance``), and distances between keypoints that the
labels show to be nearly rigid stay in the labeled set's range (``bones``). ``teacher``
pulls the network toward the pose of an exponential moving average of itself where that
teacher's views agree closely (pseudo-labels). The teacher is not stored in the
checkpoints: a resumed run restarts it from the network's weights.

The voxel cube of an unlabeled frame is placed as for prediction: ``centers = "labels"``
places it at the median centre of the training labels of the session (or of all labels),
for rigs where the animal stays within the cube; ``centers = "poses"`` takes the
per-frame cube centre (``extra/center``) of ``freipose predict``'s output for the session
(``poses``: one ``.poses.h5`` file per session, in the same order), found with the
detector, background subtraction or fixed boxes as prediction finds it.
"""

from __future__ import annotations

from dataclasses import dataclass

from freipose.io.toml import check_numbers
from freipose.nn.config_ranges import UNLABELED_RANGES


@dataclass(frozen=True)
class UnlabeledConfig:
    """Training on unlabeled clips (see the module docstring). Off without ``sessions``.

    Attributes:
        sessions: session folders (relative to the config file) to draw clips from.
        centers: ``"labels"`` (one fixed cube centre per session from the training labels)
            or ``"poses"`` (per-frame centres from ``freipose predict``'s output).
        poses: with ``centers = "poses"``: one ``.poses.h5`` file per session, in order.
        clip_frames: consecutive instants per clip (3 or more for the temporal loss).
        clip_stride: frames between the instants of a clip.
        share: share of the instants of each step that are unlabeled (0.5: as many
            unlabeled instants as labeled ones, rounded up to whole clips, at least one).
        start: fraction of the steps before the unlabeled losses act (the labeled losses
            shape the network first).
        robust_scale: scale of the robust penalty ``s log(1 + e / s)``: errors much
            larger than it (real fast movement, an occluded keypoint) count little.
        weight_multiview: each view's refined 2D point against the projection of the fused
            3D point (P1), weighted by the view's confidence, views that cannot see it left
            out. Off by default, as ``p0p1``: on the held-out synthetic mouse rig
            (``benchmarks/label_efficiency.py --ablate``, 25 labels, one seed) leaving either
            out lowered the held-out error (both logged, as every term).
        weight_p0p1: P0 against P1.
        weight_temporal: the acceleration of P1 and P0 along a clip.
        weight_equivariance: P1 and P0 of the same instant under two augmentations.
        weight_bones: nearly rigid keypoint distances outside two standard deviations of
            the labeled set's.
        weight_teacher: P0 and P1 against the teacher's P1 where its views agree.
        teacher_decay: the teacher's exponential moving average factor per step.
        teacher_agreement: a teacher keypoint is a pseudo-label when the confidence-weighted
            RMS distance of its views' points from the projections of its P1 is below this
            many feature pixels.
    """

    sessions: tuple[str, ...] = ()
    centers: str = "labels"
    poses: tuple[str, ...] = ()
    clip_frames: int = 3
    clip_stride: int = 1
    share: float = 0.5
    start: float = 0.0
    robust_scale: float = 1.0
    weight_multiview: float = 0.0
    weight_p0p1: float = 0.0
    weight_temporal: float = 0.5
    weight_equivariance: float = 0.5
    weight_bones: float = 0.5
    weight_teacher: float = 0.0
    teacher_decay: float = 0.99
    teacher_agreement: float = 0.5

    def __post_init__(self) -> None:
        check_numbers(self, "unlabeled", UNLABELED_RANGES, ValueError)
        if self.centers not in ("labels", "poses"):
            raise ValueError(f"unlabeled.centers must be 'labels' or 'poses', got {self.centers!r}")
        if self.centers == "poses" and len(self.poses) != len(self.sessions):
            raise ValueError(
                f"unlabeled.centers = 'poses' needs one poses file per session: "
                f"{len(self.sessions)} sessions, {len(self.poses)} poses files"
            )
        for name in ("clip_frames", "clip_stride"):
            if getattr(self, name) < 1:
                raise ValueError(f"unlabeled.{name} must be >= 1, got {getattr(self, name)}")

    @property
    def enabled(self) -> bool:
        """Whether the run trains on unlabeled clips."""
        return bool(self.sessions)

    def clips_per_step(self, batch_size: int) -> int:
        """Unlabeled clips per step for ``batch_size`` labeled samples (at least one).

        ``share`` of the step's instants are unlabeled, rounded up to whole clips.
        """
        want = batch_size * self.share / max(1.0 - self.share, 1e-6)
        return max(1, -(-int(round(want)) // self.clip_frames))
