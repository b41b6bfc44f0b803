"""Synthetic pose trajectories with a known stimulation effect (tests, demos, benchmarks).

A 12-keypoint rat walks around a circle with a diagonal trot; during stimulation windows one
chosen keypoint is lifted and oscillates at a chosen frequency. Running the attribution on
such recordings must rank that keypoint's variables first.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType

import numpy as np

from freipose.analysis.study import recording_entry
from freipose.io.atomic import atomic_write_text
from freipose.io.poses import PoseData, write_poses_h5
from freipose.skeleton import load_skeleton

# Rest pose in the body frame (mm): x forward, y left, z up; origin on the floor under the
# ear midpoint. Keypoint order of the shipped rat skeleton.
RAT_REST_POSE: Mapping[str, tuple[float, float, float]] = MappingProxyType(
    {
        "Ear Right": (0.0, -17.0, 55.0),
        "Eye Right": (18.0, -11.0, 48.0),
        "Paw Front Right": (8.0, -22.0, 4.0),
        "Paw Back Right Ankle": (-122.0, -28.0, 18.0),
        "Paw Back Right Tip": (-105.0, -30.0, 4.0),
        "Ear Left": (0.0, 17.0, 55.0),
        "Eye Left": (18.0, 11.0, 48.0),
        "Paw Front Left": (8.0, 22.0, 4.0),
        "Paw Back Left Ankle": (-122.0, 28.0, 18.0),
        "Paw Back Left Tip": (-105.0, 30.0, 4.0),
        "Nose": (42.0, 0.0, 40.0),
        "Tail": (-150.0, 0.0, 35.0),
    }
)
# Gait phase of each paw (diagonal trot); None = not a paw.
_PAW_PHASE: Mapping[str, float] = MappingProxyType(
    {
        "Paw Front Right": 0.0,
        "Paw Back Left Tip": 0.0,
        "Paw Back Left Ankle": 0.0,
        "Paw Front Left": np.pi,
        "Paw Back Right Tip": np.pi,
        "Paw Back Right Ankle": np.pi,
    }
)
_HEAD = ("Ear Right", "Eye Right", "Ear Left", "Eye Left", "Nose")


@dataclass(frozen=True)
class StimulusEffect:
    """What stimulation does to the simulated rat.

    Attributes:
        keypoint: the affected keypoint.
        frequency_hz: oscillation frequency of the keypoint during stimulation.
        amplitude_mm: oscillation amplitude (vertical).
        lift_mm: constant lift during stimulation.
    """

    keypoint: str = "Paw Front Right"
    frequency_hz: float = 10.0
    amplitude_mm: float = 6.0
    lift_mm: float = 8.0


def stimulation_windows(
    duration_s: float,
    first_s: float = 5.0,
    period_s: float = 10.0,
    length_s: float = 4.0,
    jitter_s: float = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """Stimulation windows inside a recording of ``duration_s`` seconds.

    One window every ``period_s`` on average, each interval varied uniformly by up to
    ``±jitter_s`` (as real protocols vary the inter-stimulus interval), the last ending at
    least 1 s before the end.

    Args:
        duration_s: length of the recording.
        first_s: start of the first window.
        period_s: mean interval between starts.
        length_s: length of every window.
        jitter_s: largest change of an interval.
        seed: random seed of the jitter.

    Returns:
        (N, 2) start/end seconds.
    """
    rng = np.random.default_rng(seed)
    starts = []
    t = first_s
    while t + length_s + 1.0 <= duration_s:
        starts.append(t)
        t += period_s + (rng.uniform(-jitter_s, jitter_s) if jitter_s else 0.0)
    s = np.asarray(starts, dtype=float)
    return np.stack([s, s + length_s], axis=1) if len(s) else np.zeros((0, 2))


def simulate_rat(
    duration_s: float,
    fps: float = 100.0,
    windows: np.ndarray | None = None,
    effect: StimulusEffect = StimulusEffect(),
    seed: int = 0,
    noise_mm: float = 1.0,
    speed_mm_s: float = 120.0,
    radius_mm: float = 300.0,
    gait_hz: float = 2.3,
) -> PoseData:
    """A walking rat (shipped ``rat`` skeleton, world z up, floor z = 0).

    Args:
        duration_s: length of the recording.
        fps: frame rate.
        windows: (N, 2) stimulation windows in seconds from the first frame.
        effect: how stimulation changes the pose.
        seed: random seed (starting position on the circle, gait phase, noise).
        noise_mm: standard deviation of the white noise added to every coordinate.
        speed_mm_s: walking speed.
        radius_mm: radius of the circle the rat walks on.
        gait_hz: step frequency.

    Returns:
        PoseData with poses (T, 12, 3), T = round(duration_s * fps).
    """
    skel = load_skeleton("rat")
    rng = np.random.default_rng(seed)
    t = np.arange(int(round(duration_s * fps))) / fps
    rest = np.array([RAT_REST_POSE[k] for k in skel.keypoints])  # (K, 3)
    body = np.broadcast_to(rest, (len(t),) + rest.shape).copy()  # (T, K, 3) body frame
    phase = 2 * np.pi * gait_hz * t + rng.uniform(0, 2 * np.pi)
    for name, ph in _PAW_PHASE.items():
        k = skel.index(name)
        body[:, k, 0] += 14.0 * np.sin(phase + ph)
        body[:, k, 2] += 10.0 * np.clip(np.cos(phase + ph), 0, None)
    for name in _HEAD:
        body[:, skel.index(name), 2] += 2.0 * np.sin(2 * phase)
    if windows is not None and len(windows):
        k = skel.index(effect.keypoint)
        for start, end in np.asarray(windows, dtype=float):
            on = (t >= start) & (t < end)
            osc = np.sin(2 * np.pi * effect.frequency_hz * (t[on] - start))
            body[on, k, 2] += effect.lift_mm + effect.amplitude_mm * osc
    # Walk around a circle, heading along the tangent.
    a0 = rng.uniform(0, 2 * np.pi)
    ang = a0 + speed_mm_s * t / radius_mm
    heading = ang + np.pi / 2
    c, s = np.cos(heading), np.sin(heading)
    world = np.empty_like(body)
    world[..., 0] = c[:, None] * body[..., 0] - s[:, None] * body[..., 1]
    world[..., 1] = s[:, None] * body[..., 0] + c[:, None] * body[..., 1]
    world[..., 2] = body[..., 2]
    world[..., 0] += (radius_mm * np.cos(ang))[:, None]
    world[..., 1] += (radius_mm * np.sin(ang))[:, None]
    world += rng.normal(0.0, noise_mm, world.shape)
    return PoseData(
        poses=world.astype(np.float32),
        confidence=np.ones(world.shape[:2], dtype=np.float32),
        keypoints=skel.keypoints,
        frame_index=np.arange(len(t)),
        fps=fps,
        up=np.array([0.0, 0.0, 1.0]),
        skeleton=skel,
        provenance={"simulated": "freipose.analysis.simulate.simulate_rat", "seed": seed},
    )


def write_events_csv(windows: np.ndarray, path: str | Path) -> None:
    """Write an ``events.csv`` (``start_s,end_s``) atomically."""
    lines = ["start_s,end_s"] + [f"{a:.6g},{b:.6g}" for a, b in np.asarray(windows)]
    atomic_write_text(path, "\n".join(lines) + "\n")


def simulate_study(
    folder: str | Path,
    animals: tuple[str, ...] = ("rat1", "rat2"),
    condition: str = "10Hz",
    duration_s: float = 60.0,
    fps: float = 100.0,
    effect: StimulusEffect = StimulusEffect(),
    seed: int = 0,
    period_s: float = 10.0,
    length_s: float = 4.0,
    jitter_s: float | None = None,
) -> Path:
    """Write a synthetic study: per animal one train and one test recording.

    Returns:
        Path of ``folder/study.toml`` (poses and events files next to it).

    ``jitter_s`` (default: a third of the gap between windows) varies the intervals.
    """
    if jitter_s is None:
        jitter_s = (period_s - length_s) / 3
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    entries = []
    for ai, animal in enumerate(animals):
        for si, split in enumerate(("train", "test")):
            name = f"{animal}_{split}"
            # Shift the windows per recording so onsets do not line up with the gait.
            k = 2 * ai + si
            win = stimulation_windows(
                duration_s, 5.0 + 0.37 * k, period_s, length_s, jitter_s, seed=seed + k
            )
            data = simulate_rat(duration_s, fps, win, effect, seed=seed + 10 * ai + si)
            write_poses_h5(data, folder / f"{name}.poses.h5")
            write_events_csv(win, folder / f"{name}_events.csv")
            entries.append(
                recording_entry(
                    name, f"{name}.poses.h5", f"{name}_events.csv", animal, condition, split
                )
            )
    path = folder / "study.toml"
    header = "# Synthetic study written by freipose.analysis.simulate.simulate_study\n\n"
    atomic_write_text(path, header + "\n".join(entries))
    return path
