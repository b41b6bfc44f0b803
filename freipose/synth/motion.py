"""Motion model of the synthetic rodent: behaviour, locomotion with a stride cycle, stimulation.

The animal alternates between walking (with smooth random turning), pausing (head scanning),
turning on the spot and rearing; it steers away from the arena walls. With a
``rest_fraction`` it also rests: seconds-long phases in which it stays almost still (the head
drifts slowly, the tail lies still), as a resting animal that background subtraction loses.
Each foot is planted on the floor while in stance and swings in an arc to a new footfall
when it falls behind its rest position (diagonal feet alternate), so feet do not slide
while standing. An optional
stimulation protocol (:class:`~freipose.synth.stimulation.StimulationConfig`) lifts/oscillates
a body part during windows of given length and spacing, with an effect growing over each
window.

The simulation runs in sub-steps of at most 10 ms; each sub-step runs the stages
:func:`_next_behaviour` (the behaviour state machine), :func:`_locomote` (speed, turning,
rearing, wall avoidance), :func:`_move_head` and :func:`_step_feet`, and every frame's last
sub-step is recorded. The random generator is drawn from in exactly this order.

Main entry points: :func:`simulate_motion` (the full :class:`MotionState`) and
:func:`simulate_trajectory` (just the 12 rat keypoints, (T, 12, 3) mm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from freipose.synth.body import RatBody, body_dims, build_body
from freipose.synth.errors import SynthError
from freipose.synth.state import MotionState
from freipose.synth.stimulation import (
    StimulationConfig,
    stimulation_effects,
    stimulation_envelope,
)


def _smoothstep(x: Any) -> Any:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


@dataclass(frozen=True, eq=False)
class _Clock:
    """Timing of a simulation: ``sub`` sub-steps of ``dt`` s per frame.

    Attributes:
        sub: sub-steps per frame.
        dt: sub-step length, s.
        n_steps: sub-steps in all (T * sub).
        t_frames: (T,) frame times, s.
        strength: (T,) stimulation strength per frame.
        since: (T,) time since the stimulation window started, per frame, s.
        step_strength: (T * sub,) stimulation strength per sub-step.
        freeze: the stimulation freezes the animal.
    """

    sub: int
    dt: float
    n_steps: int
    t_frames: np.ndarray
    strength: np.ndarray
    since: np.ndarray
    step_strength: np.ndarray
    freeze: bool


def _clock(n_frames: int, fps: float, stimulation: StimulationConfig | None) -> _Clock:
    """Sub-steps (at least 100 per second) and the stimulation's strength over time."""
    sub = max(1, math.ceil(100.0 / fps))
    t_frames = np.arange(n_frames) / fps
    env_f, since_f = stimulation_envelope(stimulation, t_frames, n_frames / fps)
    return _Clock(
        sub=sub,
        dt=1.0 / (fps * sub),
        n_steps=n_frames * sub,
        t_frames=t_frames,
        strength=env_f,
        since=since_f,
        step_strength=np.repeat(env_f, sub),
        freeze=stimulation is not None and stimulation.effect == "freeze",
    )


@dataclass(frozen=True, eq=False)
class _Space:
    """The animal's size and the arena it moves in.

    Attributes:
        s: the animal's size factor.
        half: (2,) half inner size of the arena, mm.
        margin: distance from the walls that the torso centre keeps, mm.
    """

    s: float
    half: np.ndarray
    margin: float


@dataclass(frozen=True, eq=False)
class _Gait:
    """Constants of the stepping feet.

    Attributes:
        rest_local: (4, 3) rest positions of the feet in the torso frame (front right, front
            left, hind right, hind left).
        reach: distance from its rest point at which a foot starts a swing, mm.
        swing_time: duration of a swing, s.
        lift_h: (4,) swing height of each foot, mm.
        neighbours: per foot, the feet that must be in stance for it to lift (same side and
            same girdle).
    """

    rest_local: np.ndarray
    reach: float
    swing_time: float
    lift_h: np.ndarray
    neighbours: tuple[tuple[int, int], ...]


def _gait(body: RatBody) -> _Gait:
    """The stepping constants of ``body``."""
    D = body_dims(body)
    s = D.s
    front_rest = [np.asarray(p, dtype=np.float64) for p in D.front_paw_rest]
    hind_rest = [np.asarray(p, dtype=np.float64) for p in D.hind_tip_rest]
    return _Gait(
        rest_local=np.stack(front_rest + hind_rest),
        reach=17.0 * s,
        swing_time=0.13,
        lift_h=np.array([9.0, 9.0, 11.0, 11.0]) * s,
        neighbours=((1, 2), (0, 3), (3, 0), (2, 1)),
    )


def _rest_world(rest_local: np.ndarray, x: float, y: float, yaw: float) -> np.ndarray:
    """(4, 3) rest positions of the feet in the world for the torso at ``x, y, yaw``."""
    c, sn = math.cos(yaw), math.sin(yaw)
    R = np.array([[c, -sn, 0], [sn, c, 0], [0, 0, 1]])
    return rest_local @ R.T + np.array([x, y, 0.0])


@dataclass(frozen=True)
class _Behaviour:
    """State of the behaviour state machine.

    Attributes:
        name: ``"walk"``, ``"pause"``, ``"turn"``, ``"rear"`` or ``"rest"``.
        timer: time left in this behaviour, s.
        v_target: target speed, mm/s.
        w_noise: target turning rate, rad/s.
    """

    name: str
    timer: float
    v_target: float
    w_noise: float


_MEAN_ACTIVE_S = 1.47  # mean duration of a walk, pause, turn or rear phase, s
_REST_S = (3.0, 8.0)  # duration range of a resting phase, s


def rest_probability(rest_fraction: float) -> float:
    """Probability that a new behaviour is a rest: rests then take ``rest_fraction`` of the time."""
    f = float(rest_fraction)
    if f <= 0:
        return 0.0
    mean_rest = sum(_REST_S) / 2
    return f * _MEAN_ACTIVE_S / (mean_rest * (1 - f) + f * _MEAN_ACTIVE_S)


def _next_behaviour(
    b: _Behaviour, dt: float, s: float, rng: np.random.Generator, p_rest: float = 0.0
) -> _Behaviour:
    """One sub-step of the state machine: a new random behaviour when the timer runs out.

    A new behaviour is a rest with probability ``p_rest`` (no draw when it is 0).
    """
    behaviour, b_timer, v_target, w_noise = b.name, b.timer - dt, b.v_target, b.w_noise
    if b_timer <= 0 and p_rest > 0 and rng.random() < p_rest:
        return _Behaviour("rest", float(rng.uniform(*_REST_S)), 0.0, 0.0)
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
    if behaviour == "walk" and rng.random() < dt * 1.5:
        w_noise = float(rng.normal(0, 0.7))
    return _Behaviour(behaviour, b_timer, v_target, w_noise)


@dataclass(frozen=True)
class _Pose:
    """The torso: floor position, heading, speed, turning rate and rearing.

    Attributes:
        x, y: floor point under the torso centre, mm.
        yaw: heading, rad.
        v: speed, mm/s.
        omega: turning rate, rad/s.
        rear: 0..1, how far the animal is reared up.
    """

    x: float
    y: float
    yaw: float
    v: float
    omega: float
    rear: float


def _locomote(
    p: _Pose, b: _Behaviour, strength: float, freeze: bool, dt: float, space: _Space
) -> _Pose:
    """One sub-step of the torso: first-order dynamics towards the behaviour's targets.

    The animal steers to the centre when its look-ahead point leaves the safe zone, slows
    down while frozen by a stimulation and stands still while rearing.
    """
    s, half, margin = space.s, space.half, space.margin
    x, y, yaw, v, omega, rear = p.x, p.y, p.yaw, p.v, p.omega, p.rear
    rear_target = 1.0 if b.name == "rear" and b.timer > 0.45 else 0.0
    fx, fy = math.cos(yaw), math.sin(yaw)
    look = 80.0 * s + 0.5 * v
    lx, ly = x + fx * look, y + fy * look
    vt, wt = b.v_target, b.w_noise
    if abs(lx) > half[0] - margin or abs(ly) > half[1] - margin:
        to_c = math.atan2(-y, -x)
        wt = 3.5 * _wrap(to_c - yaw)
        vt = min(vt, 110.0 * s)
    if b.name == "rest":
        vt, wt = 0.0, 0.0
    if freeze and strength > 0:
        vt, wt = vt * (1 - strength), wt * (1 - strength)
    if rear > 0.05 or rear_target > 0:
        vt, wt = 0.0, 0.0
    v += (vt - v) * min(1.0, dt / 0.3)
    omega += (wt - omega) * min(1.0, dt / 0.15)
    rear += (rear_target - rear) * min(1.0, dt / 0.28)
    yaw = _wrap(yaw + omega * dt)
    x += v * math.cos(yaw) * dt
    y += v * math.sin(yaw) * dt
    x = float(np.clip(x, -(half[0] - margin + 30 * s), half[0] - margin + 30 * s))
    y = float(np.clip(y, -(half[1] - margin + 30 * s), half[1] - margin + 30 * s))
    return _Pose(x, y, yaw, v, omega, rear)


@dataclass(frozen=True, eq=False)
class _Head:
    """The head's orientation relative to the chest and where it is turning to.

    Attributes:
        angles: (3,) yaw, pitch, roll, rad.
        target: (3,) the angles it turns to, rad.
        timer: time until the next target, s.
    """

    angles: np.ndarray
    target: np.ndarray
    timer: float


def _move_head(h: _Head, behaviour: str, dt: float, rng: np.random.Generator) -> _Head:
    """One sub-step of the head: a new random target now and then (wider when not walking)."""
    timer, target = h.timer - dt, h.target
    if timer <= 0 and behaviour == "rest":  # slow, small drifts of the head
        timer = float(rng.uniform(1.5, 4.0))
        target = h.angles + rng.uniform(-0.06, 0.06, size=3)
        return _Head(h.angles + (target - h.angles) * min(1.0, dt / 1.5), target, timer)
    if behaviour == "rest":
        return _Head(h.angles + (target - h.angles) * min(1.0, dt / 1.5), target, timer)
    if timer <= 0:
        timer = float(rng.uniform(0.25, 0.9))
        wide = behaviour != "walk"
        target = np.array([
            rng.uniform(-0.75, 0.75) if wide else rng.uniform(-0.35, 0.35),
            rng.uniform(-0.35, 0.3) if behaviour != "rear" else rng.uniform(0.0, 0.45),
            rng.uniform(-0.2, 0.2),
        ])  # fmt: skip
    return _Head(h.angles + (target - h.angles) * min(1.0, dt / 0.12), target, timer)


@dataclass(frozen=True, eq=False)
class _Feet:
    """The feet (front right, front left, hind right, hind left).

    Attributes:
        pos: (4, 3) planted or swinging positions, mm.
        foot_yaw: (2,) heading of the hind feet, rad.
        swing: (4,) swing progress in [0, 1], -1 in stance.
        swing_from: (4, 3) where each swing started, mm.
        prev_rest: (4, 3) the rest positions of the previous sub-step, mm.
    """

    pos: np.ndarray
    foot_yaw: np.ndarray
    swing: np.ndarray
    swing_from: np.ndarray
    prev_rest: np.ndarray


def _planted_feet(gait: _Gait, x: float, y: float, yaw: float) -> _Feet:
    """All feet in stance at their rest positions."""
    feet = _rest_world(gait.rest_local, x, y, yaw)
    return _Feet(feet, np.array([yaw, yaw]), np.full(4, -1.0), feet.copy(), feet.copy())


def _step_feet(ft: _Feet, p: _Pose, gait: _Gait, dt: float) -> _Feet:
    """One sub-step of the feet: stance feet stay put; one that falls behind its rest swings.

    A swinging foot lands ahead of its rest point (more so at speed); the front paws keep
    their floor point while the animal rears.
    """
    feet, foot_yaw = ft.pos.copy(), ft.foot_yaw.copy()
    swing, swing_from = ft.swing.copy(), ft.swing_from.copy()
    reach, swing_time, lift_h = gait.reach, gait.swing_time, gait.lift_h
    rest = _rest_world(gait.rest_local, p.x, p.y, p.yaw)
    vel = (rest - ft.prev_rest) / dt
    for k in range(4):
        if k < 2 and p.rear > 0.05:
            swing[k] = -1.0  # front paws are up at the chest; keep their floor point
            continue
        if swing[k] < 0:
            off = np.hypot(*(feet[k, :2] - rest[k, :2]))
            if off > reach and all(swing[j] < 0 for j in gait.neighbours[k]):
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
                foot_yaw[k - 2] = foot_yaw[k - 2] + _wrap(p.yaw - foot_yaw[k - 2]) * a
            if swing[k] >= 1.0:
                swing[k] = -1.0
                feet[k, 2] = rest[k, 2]
    return _Feet(feet, foot_yaw, swing, swing_from, rest)


@dataclass(frozen=True, eq=False)
class _Track:
    """Per-frame records of the simulation (filled frame by frame by :meth:`record`).

    Attributes:
        x, y, yaw, rear, bend, hy, hp, hr, sway_a, sway_p, curl: (T,) torso position,
            heading, rearing and bend, head yaw/pitch/roll, tail sway amplitude and phase,
            tail curl.
        feet: (T, 4, 3) feet positions, mm.
        heel: (T, 2) elevation of the hind feet, rad.
        fyaw: (T, 2) heading of the hind feet, rad.
    """

    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    rear: np.ndarray
    bend: np.ndarray
    hy: np.ndarray
    hp: np.ndarray
    hr: np.ndarray
    sway_a: np.ndarray
    sway_p: np.ndarray
    curl: np.ndarray
    feet: np.ndarray
    heel: np.ndarray
    fyaw: np.ndarray

    @classmethod
    def empty(cls, n_frames: int) -> _Track:
        """Zeros for ``n_frames`` frames."""
        names = ("x", "y", "yaw", "rear", "bend", "hy", "hp", "hr", "sway_a", "sway_p", "curl")
        return cls(
            **{k: np.zeros(n_frames) for k in names},
            feet=np.zeros((n_frames, 4, 3)),
            heel=np.zeros((n_frames, 2)),
            fyaw=np.zeros((n_frames, 2)),
        )

    def record(self, f: int, p: _Pose, head: _Head, ft: _Feet, sway_phase: float) -> None:
        """Store the state at the end of frame ``f``."""
        self.x[f], self.y[f], self.yaw[f] = p.x, p.y, p.yaw
        self.rear[f] = p.rear
        self.bend[f] = float(np.clip(0.2 * p.omega, -0.45, 0.45))
        self.hy[f], self.hp[f], self.hr[f] = head.angles
        self.sway_a[f] = 0.6 + 0.3 * math.sin(0.3 * sway_phase)
        self.sway_p[f] = sway_phase
        self.curl[f] = -1.2 * self.bend[f]
        self.feet[f] = ft.pos
        heel = [0.3 + 0.35 * math.sin(math.pi * max(0.0, ft.swing[2 + j])) for j in range(2)]
        self.heel[f] = np.array(heel) - 0.12 * p.rear
        self.fyaw[f] = ft.foot_yaw


def _simulate(
    n_frames: int,
    clock: _Clock,
    space: _Space,
    gait: _Gait,
    rng: np.random.Generator,
    start: tuple[float, float, float] | None,
    p_rest: float = 0.0,
) -> _Track:
    """Run the sub-steps of the simulation and record every frame (rests: ``p_rest``)."""
    s, half, margin, dt = space.s, space.half, space.margin, clock.dt
    if start is None:
        x, y = rng.uniform(-0.3, 0.3, size=2) * (half - margin)
        yaw = float(rng.uniform(-math.pi, math.pi))
    else:
        x, y, yaw = (float(v) for v in start)
    pose = _Pose(x, y, yaw, 0.0, 0.0, 0.0)
    behaviour = _Behaviour("pause", float(rng.uniform(0.2, 0.8)), 0.0, 0.0)
    sway_phase = float(rng.uniform(0, 2 * math.pi))
    head = _Head(np.zeros(3), np.zeros(3), 0.0)
    feet = _planted_feet(gait, x, y, yaw)
    track = _Track.empty(n_frames)
    for step in range(clock.n_steps):
        behaviour = _next_behaviour(behaviour, dt, s, rng, p_rest)
        pose = _locomote(pose, behaviour, clock.step_strength[step], clock.freeze, dt, space)
        head = _move_head(head, behaviour.name, dt, rng)
        feet = _step_feet(feet, pose, gait, dt)
        still = behaviour.name == "rest"
        sway_phase += dt * (0.02 if still else 2.0 + 0.01 * abs(pose.v))
        if (step + 1) % clock.sub == 0:
            track.record(step // clock.sub, pose, head, feet, sway_phase)
    return track


def simulate_motion(
    n_frames: int,
    fps: float,
    rng: np.random.Generator,
    body: RatBody | None = None,
    stimulation: StimulationConfig | None = None,
    arena_size: tuple[float, float] = (600.0, 600.0),
    start: tuple[float, float, float] | None = None,
    rest_fraction: float = 0.0,
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
        rest_fraction: share of the time spent resting (0: never; the classic motion).

    Returns:
        :class:`MotionState` with T frames.

    Raises:
        SynthError: ``n_frames < 1``, ``fps <= 0`` or an arena too small for the animal.
    """
    if n_frames < 1 or not fps > 0:
        raise SynthError(f"need n_frames >= 1 and fps > 0, got {n_frames} and {fps}")
    body = body or RatBody()
    s = body_dims(body).s
    half = np.asarray(arena_size, dtype=np.float64) / 2
    margin = 95.0 * s
    if np.any(half - margin < 20):
        raise SynthError(f"arena {tuple(arena_size)} mm is too small for a {s:.2f}-scale rat")
    clock = _clock(n_frames, fps, stimulation)
    if not 0.0 <= rest_fraction < 1.0:
        raise SynthError(f"rest_fraction must be in [0, 1), got {rest_fraction}")
    space, p_rest = _Space(s, half, margin), rest_probability(rest_fraction)
    tr = _simulate(n_frames, clock, space, _gait(body), rng, start, p_rest)
    return motion_state(tr, clock, stimulation, s, half)


def motion_state(
    tr: _Track, clock: _Clock, stimulation: StimulationConfig | None, s: float, half: np.ndarray
) -> MotionState:
    """The :class:`MotionState` of a recorded simulation (stimulation effects added).

    Args:
        tr: the per-frame records.
        clock: the simulation's timing and stimulation strength.
        stimulation: the protocol, or None.
        s: the animal's size factor.
        half: (2,) half inner size of the arena, mm.
    """
    effect = stimulation_effects(stimulation, clock.strength, clock.since, s, tr.yaw, tr.hp)
    return MotionState(
        root_xy=np.stack([tr.x, tr.y], -1),
        yaw=tr.yaw,
        pitch=np.deg2rad(52.0) * _smoothstep(tr.rear),
        bend=tr.bend,
        head_yaw=tr.hy,
        head_pitch=effect.head_pitch - 0.18 + 0.25 * _smoothstep(tr.rear),
        head_roll=tr.hr,
        rear_weight=_smoothstep(tr.rear * 1.4),
        feet=tr.feet,
        foot_offsets=effect.foot_offsets,
        heel_angle=tr.heel,
        foot_yaw=tr.fyaw,
        tail_sway=np.stack([tr.sway_a, tr.sway_p], -1),
        tail_curl=tr.curl,
        arena_half=(float(half[0]), float(half[1])),
        time=clock.t_frames,
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
