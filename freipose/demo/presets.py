"""The sizes of a demo run: the ``tiny`` and ``small`` presets and their sessions."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

STIM_PART = "Paw Front Right"

#: what each ``DemoSession.split`` is for (as the report says it)
SPLIT_ROLES: Mapping[str, str] = MappingProxyType({
    "label": "labeling day: the training labels come from it; not analysed",
    "train": "training day of the stimulation classifier",
    "test": "test day: held out for evaluation",
})  # fmt: skip
SPLITS = tuple(SPLIT_ROLES)


@dataclass(frozen=True)
class DemoSession:
    """One synthetic recording: its name, seed and role.

    ``split`` is ``"label"`` (the training labels come from it; not analysed: the pose
    network fits its frames better than any other recording's, which a classifier trained
    on it would learn), ``"train"`` (the classifier's training day) or ``"test"`` (held
    out: the evaluation labels and the classifier's test day).
    """

    name: str
    seed: int
    split: str

    def __post_init__(self) -> None:
        if self.split not in SPLITS:
            raise ValueError(f"demo session {self.name}: split must be one of {SPLITS}")


@dataclass(frozen=True)
class DemoPreset:
    """Sizes of a demo run.

    Attributes:
        name: preset name.
        size: image size (width, height) of the 7 cameras.
        fps: frame rate of the sessions.
        session_frames: frames of each session.
        calibration_frames: frames of the board videos.
        sessions: the recordings of one animal and condition: the labeling recording
            first (it also films the board), then the classifier's test and train days.
        stimulation: ``freipose.synth`` stimulation protocol as a dict.
        label_instants: labeled time instants imported from the labeling session.
        eval_instants: held-out time instants with true 3D keypoints for ``freipose eval``.
        pose: ``[model]`` preset and ``[schedule]`` overrides of the voxel network, and
            under ``augment`` the ``[augment]`` ones; the triangulation baseline trains with
            the same schedule and augmentation (equal budgets).
        init: starting weights of the voxel network, the baseline and the detector
            (``[model] init`` and ``[detector] init``): ``"base"`` fine-tunes the base
            models shipped in :mod:`freipose.models`, ``"scratch"`` trains from random
            weights.
        detector: the ``[detector]`` table.
        analysis: ``AttributionConfig`` fields; ``stft_window``: STFT window in frames.
        overlay_frames: frames of the overlay clip.
        batch: time steps per prediction batch.
        n_cameras: cameras of the rig.
        detection: how ``predict`` finds the animal: ``"detector"`` (the trained detector)
            or ``"bgsub"`` (background subtraction; for ``tiny``, whose few-step detector
            finds nothing).
    """

    name: str
    size: tuple[int, int]
    fps: float
    session_frames: int
    calibration_frames: int
    sessions: tuple[DemoSession, ...]
    stimulation: dict[str, Any]
    label_instants: int
    eval_instants: int
    pose: dict[str, Any]
    init: str
    detector: dict[str, Any]
    analysis: dict[str, Any]
    stft_window: int
    overlay_frames: int
    batch: int = 8
    n_cameras: int = 7
    detection: str = "detector"

    def with_split(self, *splits: str) -> tuple[DemoSession, ...]:
        """The recordings whose ``split`` is one of ``splits``, in the preset's order."""
        return tuple(s for s in self.sessions if s.split in splits)

    @property
    def analysed(self) -> tuple[DemoSession, ...]:
        """The recordings of the study (predicted and analysed): the train and test days."""
        return self.with_split("train", "test")

    def with_seed(self, seed: int) -> DemoPreset:
        """The same preset whose networks train from seed ``seed`` (0: the preset itself).

        The seed draws the networks' training samples, augmentation and (from scratch) initial
        weights; the synthetic recordings, calibration and labels stay the same, so runs with
        different seeds show how much the figures move with the training alone.
        """
        if seed == 0:
            return self
        return dataclasses.replace(
            self,
            pose={**self.pose, "seed": seed},
            detector={**self.detector, "seed": seed},
        )

    def to_dict(self) -> dict[str, Any]:
        """The preset as JSON-compatible nested dicts and lists (as stored in the markers)."""
        return json.loads(json.dumps(dataclasses.asdict(self)))


# the labels come from day 1, the classifier trains on day 3 and is tested on day 2
_SESSIONS = (
    DemoSession("rat1_day1", 1, "label"),
    DemoSession("rat1_day2", 2, "test"),
    DemoSession("rat1_day3", 3, "train"),
)

_PRESETS = {
    # End to end in a few minutes (CI): everything tiny, numbers meaningless.
    "tiny": DemoPreset(
        name="tiny",
        size=(320, 256),
        fps=25.0,
        session_frames=60,
        calibration_frames=70,
        sessions=_SESSIONS,
        stimulation=dict(
            body_part=STIM_PART,
            effect="oscillate",
            frequency_hz=5.0,
            amplitude_mm=20.0,
            duration_s=0.8,
            spacing_s=2.0,
            onset_s=0.6,
        ),  # fmt: skip
        label_instants=24,
        eval_instants=8,
        pose=dict(preset="tiny", steps=6, checkpoint_every=3, eval_every=3, eval_samples=4),
        init="scratch",  # no base is shipped for the tiny network
        detector=dict(
            input_size=64,
            width=0.25,
            neck_channels=8,
            steps=4,
            batch_size=4,
            checkpoint_every=2,
            log_every=1,
            max_images=60,
            max_eval_instants=4,
            warmup_steps=1,
            cube_size=320.0,
        ),  # fmt: skip
        analysis=dict(onset_delay_s=0.2, margin_s=0.3, pre_s=0.5, post_s=0.5, top=3),
        stft_window=16,
        overlay_frames=10,
        batch=8,
        detection="bgsub",
    ),
    # The default: the real workflow, sized to run in under 10 minutes on an idle 2-core CPU.
    "small": DemoPreset(
        name="small",
        size=(320, 256),
        fps=25.0,
        session_frames=750,
        calibration_frames=80,
        sessions=_SESSIONS,
        stimulation=dict(
            body_part=STIM_PART,
            effect="oscillate",
            frequency_hz=5.0,
            amplitude_mm=30.0,
            duration_s=2.0,
            spacing_s=2.0,
            onset_s=1.0,
        ),  # fmt: skip
        label_instants=300,
        eval_instants=60,
        # 4 of the 7 views per training sample: cheaper steps, so more of them in the
        # demo's time; the refinement head trains from the first step (the base's is
        # trained already). The demo's rat resembles the bases' training scenes, so a short
        # phase at the high rate suffices: the rate drops tenfold every 100 steps (1e-3,
        # 1e-4, 1e-5), and these 300 steps give the voxel network about the held-out error
        # of 600 steps with one drop at step 400, in half the time (the demo's runs in
        # docs/benchmarks.md). A rig unlike those scenes needs the longer schedule
        # (benchmarks/own_rig.py)
        pose=dict(
            preset="small",
            steps=300,
            lr=1e-3,
            lr_decay_steps=100,
            refine_start=0.0,
            checkpoint_every=100,
            eval_every=150,
            eval_samples=16,
            log_every=10,
            augment=dict(max_views=4),
        ),  # fmt: skip
        init="base",  # fine-tune the shipped bases (docs/models.md)
        detector=dict(
            input_size=128,
            width=0.35,
            neck_channels=24,
            steps=250,
            batch_size=8,
            checkpoint_every=50,
            log_every=10,
            max_images=1400,
            max_eval_instants=40,
            warmup_steps=20,
            cube_size=320.0,
        ),  # fmt: skip
        analysis=dict(onset_delay_s=0.6, margin_s=0.5, pre_s=1.0, post_s=1.0, top=6),
        stft_window=32,
        overlay_frames=200,  # 8 s: two stimulation windows and the pause between them
        batch=8,
    ),
}

# read-only: a preset is shared by every run that names it
PRESETS: Mapping[str, DemoPreset] = MappingProxyType(_PRESETS)
