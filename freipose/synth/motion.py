"""Motion model of the synthetic rodent: behaviour, locomotion with a stride cycle, stimulation.

The animal alternates between walking (with smooth random turning), pausing (head scanning),
turning on the spot and rearing; it steers away from the arena walls. Each foot is planted on
the floor while in stance and swings in an arc to a new footfall when it falls behind its rest
position (diagonal feet alternate), so feet do not slide while standing. An optional
stimulation protocol (:class:`StimulationConfig`) lifts/oscillates a body part during windows
of given length and spacing, with an effect growing over each window.

Main entry points: :func:`simulate_motion` (the full :class:`MotionState`) and
:func:`simulate_trajectory` (just the 12 rat keypoints, (T, 12, 3) mm).
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass

import numpy as np

from freipose.synth.body import RatBody, body_dims, build_body

log = logging.getLogger(__name__)

STIM_PARTS = ("Paw Front Right", "Paw Front Left", "Paw Back Right", "Paw Back Left", "Head")
STIM_EFFECTS = ("oscillate", "lift", "freeze")
_FOOT_INDEX = {"Paw Front Right": 0, "Paw Front Left": 1, "Paw Back Right": 2, "Paw Back Left": 3}


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
            raise ValueError(
                f"stimulation body_part must be one of {STIM_PARTS}, got {self.body_part!r}"
            )
        if self.effect not in STIM_EFFECTS:
            raise ValueError(
                f"stimulation effect must be one of {STIM_EFFECTS}, got {self.effect!r}"
            )
        if not (self.duration_s > 0 and self.spacing_s >= 0 and self.onset_s >= 0):
            raise ValueError(
                "stimulation needs duration_s > 0, spacing_s >= 0 and onset_s >= 0, got "
                f"{self.duration_s}, {self.spacing_s}, {self.onset_s}"
            )
        if self.frequency_hz < 0 or self.amplitude_mm < 0:
            raise ValueError("stimulation frequency_hz and amplitude_mm must be >= 0")
        if self.count is not None and int(self.count) < 0:
            raise ValueError(f"stimulation count must be >= 0, got {self.count}")

    def windows(self, total_s: float) -> list[tuple[float, float]]:
        """``(start_s, end_s)`` of every window that ends within ``total_s`` seconds."""
        out = []
        t = self.onset_s
        while t + self.duration_s <= total_s + 1e-9 and (
            self.count is None or len(out) < self.count
        ):
            out.append((round(t, 9), round(t + self.duration_s, 9)))
            t += self.duration_s + self.spacing_s
        return out

    def to_dict(self) -> dict:
        d = asdict(self)
        if d["count"] is None:
            del d["count"]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> StimulationConfig:
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown stimulation fields {unknown}; known: {sorted(known)}")
        return cls(**d)

    @classmethod
    def parse(cls, text: str) -> StimulationConfig:
        """From ``"key=value,key=value"`` (CLI form), e.g. ``"body_part=Head,duration_s=2"``.

        An empty string gives the defaults.
        """
        kw: dict = {}
        for item in filter(None, (s.strip() for s in text.split(","))):
            if "=" not in item:
                raise ValueError(
                    f"stimulation option {item!r} is not key=value; e.g. "
                    "'body_part=Paw Front Right,effect=oscillate,frequency_hz=10,duration_s=1'"
                )
            k, v = (s.strip() for s in item.split("=", 1))
            if k not in cls.__dataclass_fields__:
                raise ValueError(
                    f"unknown stimulation option {k!r}; known: {sorted(cls.__dataclass_fields__)}"
                )
            if k in ("body_part", "effect"):
                kw[k] = v
            elif k == "count":
                kw[k] = int(v)
            else:
                try:
                    kw[k] = float(v)
                except ValueError:
                    raise ValueError(
                        f"stimulation option {k} must be a number, got {v!r}"
                    ) from None
        return cls(**kw)


@dataclass(frozen=True, eq=False)
class MotionState:
    """Kinematic state of the animal per frame (T frames); input of ``build_body``.

    Attributes:
        root_xy: (T, 2) floor point under the torso centre, mm.
        yaw: (T,) heading (rad, 0 = +x).
        pitch: (T,) torso pitch (rad, > 0 nose up; rearing).
        bend: (T,) yaw of the chest relative to the haunch (rad).
        head_yaw, head_pitch, head_roll: (T,) head orientation relative to the chest (rad).
        rear_weight: (T,) 0..1, how far the front paws are lifted to the chest.
        feet: (T, 4, 3) planted/swinging positions of the front paw centres (right, left) and
            hind toe tips (right, left).
        foot_offsets: (T, 4, 3) stimulation offsets added to the feet.
        heel_angle: (T, 2) elevation of the hind feet (ankle above toe), rad.
        foot_yaw: (T, 2) heading of the hind feet, rad.
        tail_sway: (T, 2) sway amplitude and phase.
        tail_curl: (T,) total tail bend (rad).
        arena_half: (2,) half inner size of the arena (tail kept inside), or None.
        time: (T,) seconds.
    """

    root_xy: np.ndarray
    yaw: np.ndarray
    pitch: np.ndarray
    bend: np.ndarray
    head_yaw: np.ndarray
    head_pitch: np.ndarray
    head_roll: np.ndarray
    rear_weight: np.ndarray
    feet: np.ndarray
    foot_offsets: np.ndarray
    heel_angle: np.ndarray
    foot_yaw: np.ndarray
    tail_sway: np.ndarray
    tail_curl: np.ndarray
    arena_half: tuple[float, float] | None
    time: np.ndarray


def _smoothstep(x: np.ndarray | float) -> np.ndarray | float:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def stimulation_envelope(
    stim: StimulationConfig | None, t: np.ndarray, total_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Effect strength (T,) in [0, 1] and time since window start (T,) at times ``t`` (s).

    ``total_s`` is the recording length (windows must end within it).
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


def simulate_motion(
    n_frames: int,
    fps: float,
    rng: np.random.Generator,
    body: RatBody | None = None,
    stimulation: StimulationConfig | None = None,
    arena_size: tuple[float, float] = (600.0, 600.0),
    start: tuple[float, float, float] | None = None,
) -> MotionState:
    """Simulate ``n_frames`` of behaviour at ``fps``.

    Args:
        n_frames: number of frames T.
        fps: frames per second (the simulation runs internally at >= 100 Hz).
        rng: random generator (the only source of randomness).
        body: the animal (default: ``RatBody()``); its size sets step lengths.
        stimulation: optional stimulation protocol.
        arena_size: inner (width x, depth y) of the arena in mm, centred on the origin.
        start: optional ``(x, y, yaw)`` start; default random near the centre.

    Returns:
        :class:`MotionState` with T frames.
    """
    if n_frames < 1 or not fps > 0:
        raise ValueError(f"need n_frames >= 1 and fps > 0, got {n_frames} and {fps}")
    body = body or RatBody()
    D = body_dims(body)
    s = D.s
    half = np.asarray(arena_size, dtype=np.float64) / 2
    margin = 95.0 * s
    if np.any(half - margin < 20):
        raise ValueError(f"arena {tuple(arena_size)} mm is too small for a {s:.2f}-scale rat")
    sub = max(1, math.ceil(100.0 / fps))
    dt = 1.0 / (fps * sub)
    n_steps = n_frames * sub
    t_frames = np.arange(n_frames) / fps
    env_f, since_f = stimulation_envelope(stimulation, t_frames, n_frames / fps)
    env = np.repeat(env_f, sub)
    freeze = stimulation is not None and stimulation.effect == "freeze"

    # state
    if start is None:
        x, y = rng.uniform(-0.3, 0.3, size=2) * (half - margin)
        yaw = float(rng.uniform(-math.pi, math.pi))
    else:
        x, y, yaw = (float(v) for v in start)
    v = 0.0
    omega = 0.0
    rear = 0.0
    head = np.zeros(3)  # yaw, pitch, roll
    head_target = np.zeros(3)
    head_timer = 0.0
    behaviour, b_timer = "pause", float(rng.uniform(0.2, 0.8))
    v_target, rear_target = 0.0, 0.0
    w_noise = 0.0
    sway_phase = float(rng.uniform(0, 2 * math.pi))

    front_rest = [np.asarray(p, dtype=np.float64) for p in D.front_paw_rest]
    hind_rest = [np.asarray(p, dtype=np.float64) for p in D.hind_tip_rest]
    rest_local = np.stack(front_rest + hind_rest)  # (4, 3) torso frame

    def rest_world(x: float, y: float, yaw: float) -> np.ndarray:
        c, sn = math.cos(yaw), math.sin(yaw)
        R = np.array([[c, -sn, 0], [sn, c, 0], [0, 0, 1]])
        return rest_local @ R.T + np.array([x, y, 0.0])

    feet = rest_world(x, y, yaw)
    foot_yaw = np.array([yaw, yaw])
    swing = np.full(4, -1.0)  # swing progress in [0, 1), -1 = stance
    swing_from = feet.copy()
    reach = 17.0 * s
    swing_time = 0.13
    lift_h = np.array([9.0, 9.0, 11.0, 11.0]) * s
    # feet that must be in stance for a foot to lift: same side and same girdle
    neighbours = {0: (1, 2), 1: (0, 3), 2: (3, 0), 3: (2, 1)}
    prev_rest = feet.copy()

    out = {
        k: np.zeros(n_frames)
        for k in ("x", "y", "yaw", "rear", "bend", "hy", "hp", "hr", "sway_a", "sway_p", "curl")
    }
    out_feet = np.zeros((n_frames, 4, 3))
    out_heel = np.zeros((n_frames, 2))
    out_fyaw = np.zeros((n_frames, 2))

    for step in range(n_steps):
        # -- behaviour state machine
        b_timer -= dt
        if b_timer <= 0:
            r = rng.random()
            if r < 0.45:
                behaviour, b_timer = "walk", float(rng.uniform(0.8, 3.0))
                v_target = float(rng.uniform(60, 220)) * s
                w_noise = float(rng.normal(0, 0.6))
            elif r < 0.68:
                behaviour, b_timer = "pause", float(rng.uniform(0.4, 1.8))
                v_target, w_noise = 0.0, 0.0
            elif r < 0.84:
                behaviour, b_timer = "turn", float(rng.uniform(0.4, 1.0))
                v_target = float(rng.uniform(0, 30)) * s
                w_noise = float(rng.choice([-1, 1]) * rng.uniform(1.5, 3.0))
            else:
                behaviour, b_timer = "rear", float(rng.uniform(0.9, 2.2))
                v_target, w_noise = 0.0, 0.0
        rear_target = 1.0 if behaviour == "rear" and b_timer > 0.45 else 0.0
        if behaviour == "walk" and rng.random() < dt * 1.5:
            w_noise = float(rng.normal(0, 0.7))

        # -- wall avoidance: steer to the centre when the look-ahead point leaves the safe zone
        fx, fy = math.cos(yaw), math.sin(yaw)
        look = 80.0 * s + 0.5 * v
        lx, ly = x + fx * look, y + fy * look
        vt, wt = v_target, w_noise
        if abs(lx) > half[0] - margin or abs(ly) > half[1] - margin:
            to_c = math.atan2(-y, -x)
            wt = 3.5 * _wrap(to_c - yaw)
            vt = min(vt, 110.0 * s)
        if freeze and env[step] > 0:
            vt, wt = vt * (1 - env[step]), wt * (1 - env[step])
        if rear > 0.05 or rear_target > 0:
            vt, wt = 0.0, 0.0
        # -- first-order dynamics
        v += (vt - v) * min(1.0, dt / 0.3)
        omega += (wt - omega) * min(1.0, dt / 0.15)
        rear += (rear_target - rear) * min(1.0, dt / 0.28)
        yaw = _wrap(yaw + omega * dt)
        x += v * math.cos(yaw) * dt
        y += v * math.sin(yaw) * dt
        x = float(np.clip(x, -(half[0] - margin + 30 * s), half[0] - margin + 30 * s))
        y = float(np.clip(y, -(half[1] - margin + 30 * s), half[1] - margin + 30 * s))

        # -- head: new random target now and then; looks around more when not walking
        head_timer -= dt
        if head_timer <= 0:
            head_timer = float(rng.uniform(0.25, 0.9))
            wide = behaviour != "walk"
            head_target = np.array([
                rng.uniform(-0.75, 0.75) if wide else rng.uniform(-0.35, 0.35),
                rng.uniform(-0.35, 0.3) if behaviour != "rear" else rng.uniform(0.0, 0.45),
                rng.uniform(-0.2, 0.2),
            ])  # fmt: skip
        head += (head_target - head) * min(1.0, dt / 0.12)

        # -- feet: stance feet stay put; a foot that falls behind its rest point swings
        rest = rest_world(x, y, yaw)
        vel = (rest - prev_rest) / dt
        prev_rest = rest
        for k in range(4):
            if k < 2 and rear > 0.05:
                swing[k] = -1.0  # front paws are up at the chest; keep their floor point
                continue
            if swing[k] < 0:
                off = np.hypot(*(feet[k, :2] - rest[k, :2]))
                if off > reach and all(swing[j] < 0 for j in neighbours[k]):
                    swing[k] = 0.0
                    swing_from[k] = feet[k].copy()
            if swing[k] >= 0:
                swing[k] = min(1.0, swing[k] + dt / swing_time)
                spd = np.hypot(*vel[k, :2])
                ahead = vel[k] * (1 - swing[k]) * swing_time
                if spd > 1e-6:
                    ahead = ahead + vel[k] / spd * min(0.8 * reach, spd * 0.15)
                target = rest[k] + ahead
                a = _smoothstep(swing[k])
                feet[k] = swing_from[k] + (target - swing_from[k]) * a
                feet[k, 2] = rest[k, 2] + lift_h[k] * math.sin(math.pi * swing[k])
                if k >= 2:
                    foot_yaw[k - 2] = foot_yaw[k - 2] + _wrap(yaw - foot_yaw[k - 2]) * a
                if swing[k] >= 1.0:
                    swing[k] = -1.0
                    feet[k, 2] = rest[k, 2]
        sway_phase += dt * (2.0 + 0.01 * abs(v))

        if (step + 1) % sub == 0:
            f = step // sub
            out["x"][f], out["y"][f], out["yaw"][f] = x, y, yaw
            out["rear"][f] = rear
            out["bend"][f] = float(np.clip(0.2 * omega, -0.45, 0.45))
            out["hy"][f], out["hp"][f], out["hr"][f] = head
            out["sway_a"][f] = 0.6 + 0.3 * math.sin(0.3 * sway_phase)
            out["sway_p"][f] = sway_phase
            out["curl"][f] = -1.2 * out["bend"][f]
            out_feet[f] = feet
            heel = [0.3 + 0.35 * math.sin(math.pi * max(0.0, swing[2 + j])) for j in range(2)]
            out_heel[f] = np.array(heel) - 0.12 * rear
            out_fyaw[f] = foot_yaw

    # stimulation effects on body parts
    offsets = np.zeros((n_frames, 4, 3))
    head_pitch = out["hp"].copy()
    if stimulation is not None and stimulation.effect != "freeze":
        A = stimulation.amplitude_mm * s
        ph = 2 * math.pi * stimulation.frequency_hz * since_f
        if stimulation.effect == "oscillate":
            up = env_f * A * (0.6 + 0.4 * np.sin(ph))
            fwd = env_f * 0.3 * A * np.cos(ph)
        else:
            up, fwd = env_f * A, np.zeros(n_frames)
        if stimulation.body_part == "Head":
            head_pitch = head_pitch + up / (40.0 * s)
        else:
            k = _FOOT_INDEX[stimulation.body_part]
            offsets[:, k, 2] = up
            offsets[:, k, 0] = fwd * np.cos(out["yaw"])
            offsets[:, k, 1] = fwd * np.sin(out["yaw"])

    pitch = np.deg2rad(52.0) * _smoothstep(out["rear"])
    return MotionState(
        root_xy=np.stack([out["x"], out["y"]], -1),
        yaw=out["yaw"],
        pitch=pitch,
        bend=out["bend"],
        head_yaw=out["hy"],
        head_pitch=head_pitch - 0.18 + 0.25 * _smoothstep(out["rear"]),
        head_roll=out["hr"],
        rear_weight=_smoothstep(out["rear"] * 1.4),
        feet=out_feet,
        foot_offsets=offsets,
        heel_angle=out_heel,
        foot_yaw=out_fyaw,
        tail_sway=np.stack([out["sway_a"], out["sway_p"]], -1),
        tail_curl=out["curl"],
        arena_half=(float(half[0]), float(half[1])),
        time=t_frames,
    )


def simulate_trajectory(
    n_frames: int,
    fps: float,
    rng: np.random.Generator | int | None = None,
    stimulation: StimulationConfig | None = None,
    body: RatBody | None = None,
    arena_size: tuple[float, float] = (600.0, 600.0),
) -> np.ndarray:
    """Keypoint trajectory of a behaving rat: (T, 12, 3) world mm, rat skeleton order.

    Walking with a stride cycle, turning, rearing, head movements and pauses over an arena
    floor at z = 0 (z up); feet rest on the floor when standing and no body part goes below
    the floor. ``rng`` may be a seed.
    """
    rng = np.random.default_rng(rng) if not isinstance(rng, np.random.Generator) else rng
    state = simulate_motion(n_frames, fps, rng, body, stimulation, arena_size)
    return build_body(body or RatBody(), state).keypoints
