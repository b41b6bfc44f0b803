"""Stimulation protocols of the synthetic rodent: windows during which an effect acts.

A :class:`StimulationConfig` lifts or oscillates a body part (or freezes the animal)
during windows of given length and spacing; the effect grows linearly over each window
and fades out in 0.1 s after it. :func:`stimulation_envelope` gives the effect's strength
over time, :func:`stimulation_effects` the offsets it adds to the feet or the head.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from types import MappingProxyType
from typing import Any

import numpy as np

from freipose.io.toml import dataclass_from_table
from freipose.synth.errors import SynthError

STIM_PARTS = ("Paw Front Right", "Paw Front Left", "Paw Back Right", "Paw Back Left", "Head")
STIM_EFFECTS = ("oscillate", "lift", "freeze")
FOOT_INDEX: Mapping[str, int] = MappingProxyType(
    {"Paw Front Right": 0, "Paw Front Left": 1, "Paw Back Right": 2, "Paw Back Left": 3}
)


@dataclass(frozen=True)
class StimulationConfig:
    """A stimulation protocol: windows during which an effect acts on a body part.

    Attributes:
        body_part: one of ``STIM_PARTS`` (``"Paw Front Right"`` ... ``"Head"``).
        effect: ``"oscillate"`` (lifted and oscillating at ``frequency_hz``), ``"lift"``
            (raised) or ``"freeze"`` (the animal stops moving); the effect grows linearly
            over each window and fades out in 0.1 s after it.
        frequency_hz: oscillation frequency.
        amplitude_mm: lift/oscillation amplitude at the end of a window (radians x 40 for the
            head).
        duration_s: window length.
        spacing_s: pause between the end of one window and the start of the next.
        onset_s: start of the first window.
        count: number of windows (None: as many as fit into the recording).
    """

    body_part: str = "Paw Front Right"
    effect: str = "oscillate"
    frequency_hz: float = 10.0
    amplitude_mm: float = 12.0
    duration_s: float = 1.0
    spacing_s: float = 2.0
    onset_s: float = 1.0
    count: int | None = None

    def __post_init__(self) -> None:
        if self.body_part not in STIM_PARTS:
            raise SynthError(
                f"stimulation body_part must be one of {STIM_PARTS}, got {self.body_part!r}"
            )
        if self.effect not in STIM_EFFECTS:
            raise SynthError(
                f"stimulation effect must be one of {STIM_EFFECTS}, got {self.effect!r}"
            )
        if not (self.duration_s > 0 and self.spacing_s >= 0 and self.onset_s >= 0):
            raise SynthError(
                "stimulation needs duration_s > 0, spacing_s >= 0 and onset_s >= 0, got "
                f"{self.duration_s}, {self.spacing_s}, {self.onset_s}"
            )
        if self.frequency_hz < 0 or self.amplitude_mm < 0:
            raise SynthError("stimulation frequency_hz and amplitude_mm must be >= 0")
        if self.count is not None and int(self.count) < 0:
            raise SynthError(f"stimulation count must be >= 0, got {self.count}")

    def windows(self, total_s: float) -> list[tuple[float, float]]:
        """``(start_s, end_s)`` of every window that ends within ``total_s`` seconds."""
        out: list[tuple[float, float]] = []
        t = self.onset_s
        while t + self.duration_s <= total_s + 1e-9 and (
            self.count is None or len(out) < self.count
        ):
            out.append((round(t, 9), round(t + self.duration_s, 9)))
            t += self.duration_s + self.spacing_s
        return out

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (TOML-serializable; no ``count`` when it is None)."""
        d = asdict(self)
        if d["count"] is None:
            del d["count"]
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> StimulationConfig:
        """The protocol of the plain dict ``d`` (as written by :meth:`to_dict`).

        Raises:
            SynthError: an unknown or invalid field.
        """
        return dataclass_from_table(cls, d, "stimulation", SynthError)

    @classmethod
    def parse(cls, text: str) -> StimulationConfig:
        """From ``"key=value,key=value"`` (CLI form), e.g. ``"body_part=Head,duration_s=2"``.

        An empty string gives the defaults.

        Raises:
            SynthError: an item that is not ``key=value``, an unknown key or a bad value.
        """
        names = sorted(f.name for f in fields(cls))
        kw: dict[str, Any] = {}
        for item in filter(None, (s.strip() for s in text.split(","))):
            if "=" not in item:
                raise SynthError(
                    f"stimulation option {item!r} is not key=value; e.g. "
                    "'body_part=Paw Front Right,effect=oscillate,frequency_hz=10,duration_s=1'"
                )
            k, v = (s.strip() for s in item.split("=", 1))
            if k not in names:
                raise SynthError(f"unknown stimulation option {k!r}; known: {names}")
            if k in ("body_part", "effect"):
                kw[k] = v
            elif k == "count":
                kw[k] = int(v)
            else:
                try:
                    kw[k] = float(v)
                except ValueError:
                    raise SynthError(
                        f"stimulation option {k} must be a number, got {v!r}"
                    ) from None
        return cls(**kw)


def stimulation_envelope(
    stim: StimulationConfig | None, t: np.ndarray, total_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Effect strength (T,) in [0, 1] and time since window start (T,) at times ``t`` (s).

    Args:
        stim: the protocol, or None (no stimulation: zeros).
        t: (T,) times, s.
        total_s: the recording length (windows must end within it).

    Returns:
        ``(strength (T,), since (T,))``.
    """
    env = np.zeros_like(t)
    since = np.zeros_like(t)
    if stim is None:
        return env, since
    for start, end in stim.windows(total_s):
        inside = (t >= start) & (t < end)
        env[inside] = (t[inside] - start) / (end - start)
        since[inside] = t[inside] - start
        fade = (t >= end) & (t < end + 0.1)
        env[fade] = np.maximum(env[fade], 1.0 - (t[fade] - end) / 0.1)
        since[fade] = t[fade] - start
    return env, since


@dataclass(frozen=True, eq=False)
class StimulationEffect:
    """What a stimulation adds to the motion, per frame.

    Attributes:
        foot_offsets: (T, 4, 3) offsets of the feet (front right, front left, hind right,
            hind left), mm.
        head_pitch: (T,) head pitch with the stimulation's lift, rad.
    """

    foot_offsets: np.ndarray
    head_pitch: np.ndarray


def stimulation_effects(
    stim: StimulationConfig | None,
    strength: np.ndarray,
    since: np.ndarray,
    scale: float,
    yaw: np.ndarray,
    head_pitch: np.ndarray,
) -> StimulationEffect:
    """The foot offsets and head pitch of a stimulated animal (freezing moves no part).

    Args:
        stim: the protocol, or None.
        strength: (T,) effect strength (:func:`stimulation_envelope`).
        since: (T,) time since the window start, s.
        scale: the animal's size factor (amplitudes scale with it).
        yaw: (T,) heading of the animal, rad.
        head_pitch: (T,) head pitch without stimulation, rad.

    Returns:
        :class:`StimulationEffect`.
    """
    n_frames = len(strength)
    offsets = np.zeros((n_frames, 4, 3))
    head_pitch = head_pitch.copy()
    if stim is not None and stim.effect != "freeze":
        A = stim.amplitude_mm * scale
        ph = 2 * math.pi * stim.frequency_hz * since
        if stim.effect == "oscillate":
            up = strength * A * (0.6 + 0.4 * np.sin(ph))
            fwd = strength * 0.3 * A * np.cos(ph)
        else:
            up, fwd = strength * A, np.zeros(n_frames)
        if stim.body_part == "Head":
            head_pitch = head_pitch + up / (40.0 * scale)
        else:
            k = FOOT_INDEX[stim.body_part]
            offsets[:, k, 2] = up
            offsets[:, k, 0] = fwd * np.cos(yaw)
            offsets[:, k, 1] = fwd * np.sin(yaw)
    return StimulationEffect(offsets, head_pitch)


__all__ = [
    "STIM_EFFECTS",
    "STIM_PARTS",
    "StimulationConfig",
    "StimulationEffect",
    "stimulation_effects",
    "stimulation_envelope",
]
