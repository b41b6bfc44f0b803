"""Synthetic stimulation studies as poses files: several animals, days and trials, no pixels.

A :class:`StudyPreset` names the animals, the recording days per animal and the
stimulation protocol; :func:`write_study` writes every recording's keypoints (the true
trajectories of :func:`~freipose.synth.motion.simulate_motion`, each animal its own body)
as a poses file with its ``events.csv``, and the ``study.toml`` of ``freipose analyze``.
The first days of every animal train the classifier, the later ones test it.

Predicting many rendered sessions costs far more than analysing them, so the poses may
instead carry a model of a pose network's error: per keypoint and axis a first-order
autoregressive error (standard deviation ``error_mm``, correlation time ``error_tau_s``),
which persists over several frames as a network's error does.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

from freipose.io.atomic import atomic_write_text
from freipose.io.poses import PoseData, write_poses_h5
from freipose.skeleton import load_skeleton
from freipose.synth.body import RatBody, build_body
from freipose.synth.errors import SynthError
from freipose.synth.motion import simulate_motion
from freipose.synth.stimulation import StimulationConfig

# median 3D error of an error model with standard deviation 1 per axis (Maxwell median)
MAXWELL_MEDIAN = 1.5382


@dataclass(frozen=True)
class StudyPreset:
    """The design of a synthetic study.

    Attributes:
        name: the preset's name.
        animals: number of animals.
        days: recordings per animal; the first ``train_days`` train the classifier.
        train_days: the train recordings of every animal.
        frames: frames of a recording.
        fps: frame rate.
        stimulation: the protocol (:class:`~freipose.synth.stimulation.StimulationConfig`
            fields); every recording starts its first window at a random time in its first
            pause, so the schedules differ.
        error_mm: standard deviation per axis of the pose error model (0: true poses).
        error_tau_s: correlation time of the pose error.
    """

    name: str
    animals: int
    days: int
    train_days: int
    frames: int
    fps: float
    stimulation: Mapping[str, Any]
    error_mm: float = 0.0
    error_tau_s: float = 0.2

    def __post_init__(self) -> None:
        if self.animals < 1 or not 1 <= self.train_days < self.days:
            raise SynthError(
                f"study preset {self.name}: needs at least one animal and 1 <= train_days < "
                f"days, got {self.animals} animals, {self.train_days} of {self.days} days"
            )

    @property
    def trials_per_recording(self) -> int:
        """Stimulation windows in one recording (the first window at its latest start)."""
        stim = StimulationConfig.from_dict(dict(self.stimulation))
        late = dataclasses.replace(stim, onset_s=stim.onset_s + stim.spacing_s)
        return len(late.windows(self.frames / self.fps))


# The demo's protocol (5 Hz, 30 mm oscillation of the front right paw, 2 s on / 2 s off)
# and the demo network's error (median 3D error 5 mm, persisting over about 0.2 s).
_DEMO_STIM = MappingProxyType(dict(body_part="Paw Front Right", effect="oscillate",
                                   frequency_hz=5.0, amplitude_mm=30.0, duration_s=2.0,
                                   spacing_s=2.0, onset_s=1.0))  # fmt: skip
_DEMO_ERROR = 5.0 / MAXWELL_MEDIAN

STUDY_PRESETS: Mapping[str, StudyPreset] = MappingProxyType({
    # the demo's design: one animal, a train and a test day of 30 s (7 trials each)
    "pilot": StudyPreset("pilot", 1, 2, 1, 750, 25.0, _DEMO_STIM, _DEMO_ERROR),
    # sized by `freipose analyze design` on the pilot (the paw's best variable, an effect
    # of 1.9 SD): 56 trials per animal in recordings of the pilot's length (7 trials each)
    # give power 1.00 (0.96-1.00) with 3 animals, 28 trials 0.20
    "study": StudyPreset("study", 3, 8, 4, 750, 25.0, _DEMO_STIM, _DEMO_ERROR),
})  # fmt: skip


def ar1_error(
    shape: tuple[int, ...], sd: float, tau_frames: float, rng: np.random.Generator
) -> np.ndarray:
    """A stationary first-order autoregressive error along the first axis.

    Args:
        shape: (T, ...) output shape.
        sd: standard deviation of every element.
        tau_frames: correlation time in frames (correlation ``exp(-1/tau)`` at lag 1).
        rng: random generator.

    Returns:
        The error, float64.
    """
    phi = math.exp(-1.0 / tau_frames) if tau_frames > 0 else 0.0
    shocks = rng.normal(0.0, sd * math.sqrt(1 - phi * phi), shape)
    out = np.empty(shape)
    out[0] = rng.normal(0.0, sd, shape[1:])
    for t in range(1, shape[0]):
        out[t] = phi * out[t - 1] + shocks[t]
    return out


def recording_stimulation(preset: StudyPreset, rng: np.random.Generator) -> StimulationConfig:
    """One recording's protocol: the preset's, its first window at a random time in its first pause.

    Args:
        preset: the design.
        rng: the recording's random generator (draws the onset first).

    Returns:
        The protocol of the recording (``onset_s`` plus a uniform draw up to ``spacing_s``).
    """
    stim = StimulationConfig.from_dict(dict(preset.stimulation))
    return dataclasses.replace(stim, onset_s=stim.onset_s + float(rng.uniform(0, stim.spacing_s)))


def _manifest_entry(name: str, animal: str, condition: str, split: str) -> str:
    values = dict(name=name, poses=f"{name}.poses.h5", events=f"{name}_events.csv",
                  animal=animal, condition=condition, split=split)  # fmt: skip
    return "[[recordings]]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in values.items())


def _recording(
    preset: StudyPreset, body: RatBody, seed: int, with_error: bool
) -> tuple[np.ndarray, list[tuple[float, float]]]:
    """One recording's poses (T, 12, 3) and stimulation windows."""
    rng = np.random.default_rng(seed)
    stim = recording_stimulation(preset, rng)
    state = simulate_motion(preset.frames, preset.fps, rng, body, stim)
    poses = build_body(body, state).keypoints
    if with_error and preset.error_mm > 0:
        poses = poses + ar1_error(
            poses.shape, preset.error_mm, preset.error_tau_s * preset.fps, rng
        )
    return poses.astype(np.float32), stim.windows(preset.frames / preset.fps)


def write_study(
    folder: str | Path, preset: StudyPreset, seed: int = 0, with_error: bool = True
) -> Path:
    """Write the poses, events and ``study.toml`` of a synthetic study.

    Args:
        folder: the output folder (created).
        preset: the design.
        seed: random seed (the animals' bodies, their motion, the schedules, the errors).
        with_error: add the preset's pose error model (False: the true keypoints).

    Returns:
        The path of ``study.toml``.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    skel = load_skeleton("rat")
    condition = f"{preset.stimulation['body_part']} {preset.stimulation['effect']}"
    entries = []
    for a in range(preset.animals):
        animal = f"rat{a + 1}"
        body = RatBody.random(np.random.default_rng([seed, a, 0]))
        for d in range(preset.days):
            name = f"{animal}_day{d + 1}"
            poses, windows = _recording(
                preset,
                body,
                int(np.random.default_rng([seed, a, d + 1]).integers(2**31)),
                with_error,
            )
            data = PoseData(
                poses=poses, confidence=np.ones(poses.shape[:2], np.float32),
                keypoints=skel.keypoints, frame_index=np.arange(len(poses)), fps=preset.fps,
                skeleton=skel,
                provenance={"synthetic study": preset.name, "seed": seed,
                            "pose error mm": preset.error_mm if with_error else 0.0},
            )  # fmt: skip
            write_poses_h5(data, folder / f"{name}.poses.h5")
            lines = ["start_s,end_s"] + [f"{s:.6f},{e:.6f}" for s, e in windows]
            atomic_write_text(folder / f"{name}_events.csv", "\n".join(lines) + "\n")
            split = "train" if d < preset.train_days else "test"
            entries.append(_manifest_entry(name, animal, condition, split))
    path = folder / "study.toml"
    header = (f"# synthetic study, preset {preset.name!r}, seed {seed}: {preset.animals} animals x "
              f"{preset.days} days\nskeleton = \"rat\"\n\n")  # fmt: skip
    atomic_write_text(path, header + "\n".join(entries))
    return path
