"""Several synthetic animals in one arena: meeting, crossing, climbing over, occluding.

:func:`simulate_social` runs the motion model of :mod:`freipose.synth.motion` for 2-4
animals in one loop of sub-steps, with social rules on top:

* **meeting**: a new walk heads for another animal (chosen at random) with probability
  ``approach``: for its head, its tail base or its flank (social investigation), steering
  there until it is reached or the walk ends;
* **contact**: each animal's floor print is three discs (haunch, chest, head) in its torso
  frame; two animals whose discs overlap are pushed apart (at most 2 mm per sub-step each,
  so they slide past each other: crossing), unless
* **climbing**: at the start of a contact, with probability ``climb``, the faster animal
  climbs over the other: it walks on straight, is not pushed, and is raised by the other's
  back height times how far its torso is over the other's (smoothed over 0.2 s); the climb
  ends when their prints separate, or after 3 s.

:func:`combine_geometries` joins the animals' :class:`~freipose.synth.body.BodyGeometry` s
into one (their parts and keypoints one animal after the other; animal ``a``'s materials
offset by ``a * len(MATERIALS)``, its palette rows those of :func:`combined_palette`), which
the renderer (:mod:`freipose.synth.render`) and the exact visibility test
(:func:`freipose.synth.visibility.keypoint_visibility`) take as they take one animal: the
animals hide each other exactly as the renderer's depth test shows them.

A stimulation acts on the first animal only.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from freipose.synth.body import BodyGeometry, RatBody, body_dims
from freipose.synth.coats import MATERIALS
from freipose.synth.errors import SynthError
from freipose.synth.motion import (
    _Behaviour,
    _clock,
    _gait,
    _Head,
    _locomote,
    _move_head,
    _next_behaviour,
    _planted_feet,
    _Pose,
    _smoothstep,
    _Space,
    _step_feet,
    _Track,
    _wrap,
    motion_state,
    rest_probability,
)
from freipose.synth.state import MotionState
from freipose.synth.stimulation import StimulationConfig

MAX_ANIMALS = 4
_CLIMB_MAX_S = 3.0
_PUSH_MM = 2.0  # the most an animal is pushed per sub-step (200 mm/s at 100 sub-steps/s)


@dataclass(frozen=True, eq=False)
class SocialMotion:
    """The motion of several animals.

    Attributes:
        states: (A,) each animal's :class:`MotionState` (T frames).
        lift: (T, A) how far each animal is raised (climbing on another's back), mm.
        on_top_of: (T, A) int, the animal each one climbs over, -1 when none.
        contact: (T, A, A) bool, the animals' floor prints overlap (climbing or pushed).
    """

    states: tuple[MotionState, ...]
    lift: np.ndarray
    on_top_of: np.ndarray
    contact: np.ndarray


def _prints(body: RatBody) -> tuple[np.ndarray, np.ndarray]:
    """The floor print of ``body``: (3, 2) disc centres in the torso frame and (3,) radii, mm."""
    D = body_dims(body)
    L = body.scale * body.length
    G = body.scale * body.girth
    centres = np.array([[-32 * L, 0.0], [22 * L, 0.0], [D.neck[0] + 24 * body.scale, 0.0]])
    return centres, np.array([34 * G, 28 * G, 18 * body.scale])


def _world_prints(local: np.ndarray, p: _Pose) -> np.ndarray:
    """(3, 2) world centres of the print discs of an animal at pose ``p``."""
    c, s = math.cos(p.yaw), math.sin(p.yaw)
    return local @ np.array([[c, s], [-s, c]]) + np.array([p.x, p.y])


def _gap(a: np.ndarray, ra: np.ndarray, b: np.ndarray, rb: np.ndarray) -> tuple[float, np.ndarray]:
    """Smallest gap between two prints (negative: overlap, mm) and the unit push a <- b."""
    d = a[:, None] - b[None]  # (3, 3, 2)
    dist = np.linalg.norm(d, axis=-1)
    gap = dist - (ra[:, None] + rb[None])
    i, j = np.unravel_index(int(np.argmin(gap)), gap.shape)
    v = d[i, j] / max(float(dist[i, j]), 1e-6)
    return float(gap[i, j]), v


@dataclass
class _Animal:
    """The mutable state of one animal in the joint loop."""

    pose: _Pose
    behaviour: _Behaviour
    head: _Head
    feet: object
    sway: float
    target: int = -1
    aim: float = 0.0  # where on the target: mm ahead of its torso centre along its heading
    climb: int = -1
    climb_t: float = 0.0


def _start_poses(
    n: int, half: np.ndarray, margin: float, rng: np.random.Generator
) -> list[tuple[float, float, float]]:
    """Start positions spread around the arena centre, headings at random."""
    r = 0.55 * float(np.min(half - margin))
    a0 = float(rng.uniform(-math.pi, math.pi))
    out = []
    for i in range(n):
        a = a0 + 2 * math.pi * i / n + float(rng.uniform(-0.3, 0.3))
        out.append((r * math.cos(a), r * math.sin(a), float(rng.uniform(-math.pi, math.pi))))
    return out


def simulate_social(
    n_frames: int,
    fps: float,
    rngs: Sequence[np.random.Generator],
    social_rng: np.random.Generator,
    bodies: Sequence[RatBody],
    arena_size: tuple[float, float] = (600.0, 600.0),
    stimulation: StimulationConfig | None = None,
    rest_fraction: float = 0.0,
    approach: float = 0.5,
    climb: float = 0.35,
) -> SocialMotion:
    """Simulate ``len(bodies)`` animals together (see the module docstring).

    Args:
        n_frames: frames T.
        fps: frames per second.
        rngs: (A,) each animal's random generator (its behaviour).
        social_rng: the generator of the start positions and the social choices.
        bodies: (A,) the animals, 2..4.
        arena_size: inner (x, y) of the arena, mm.
        stimulation: protocol for the first animal, or None.
        rest_fraction: share of the time each animal rests.
        approach: probability that a new walk heads for another animal.
        climb: probability that a contact becomes a climb over the other animal.

    Returns:
        :class:`SocialMotion`.

    Raises:
        SynthError: not 2..4 animals, or an arena too small for them.
    """
    n = len(bodies)
    if not 2 <= n <= MAX_ANIMALS or len(rngs) != n:
        raise SynthError(f"a social scene has 2..{MAX_ANIMALS} animals, got {n}")
    if n_frames < 1 or not fps > 0:
        raise SynthError(f"need n_frames >= 1 and fps > 0, got {n_frames} and {fps}")
    half = np.asarray(arena_size, dtype=np.float64) / 2
    sizes = [body_dims(b).s for b in bodies]
    margins = [95.0 * s for s in sizes]
    if np.any(half - max(margins) < 20):
        raise SynthError(
            f"arena {tuple(arena_size)} mm is too small for animals of scale {max(sizes):.2f}; "
            f"give a larger arena_size"
        )
    clocks = [_clock(n_frames, fps, stimulation if a == 0 else None) for a in range(n)]
    dt, sub = clocks[0].dt, clocks[0].sub
    spaces = [_Space(s, half, m) for s, m in zip(sizes, margins)]
    gaits = [_gait(b) for b in bodies]
    prints = [_prints(b) for b in bodies]
    heights = np.array([70.0 * b.scale * b.girth for b in bodies])  # top of the back, mm
    p_rest = rest_probability(rest_fraction)
    animals = []
    for a, (x, y, yaw) in enumerate(_start_poses(n, half, max(margins), social_rng)):
        rng = rngs[a]
        animals.append(
            _Animal(
                _Pose(x, y, yaw, 0.0, 0.0, 0.0),
                _Behaviour("pause", float(rng.uniform(0.2, 0.8)), 0.0, 0.0),
                _Head(np.zeros(3), np.zeros(3), 0.0),
                _planted_feet(gaits[a], x, y, yaw),
                float(rng.uniform(0, 2 * math.pi)),
            )
        )
    tracks = [_Track.empty(n_frames) for _ in range(n)]
    on_top = np.full((n_frames, n), -1, np.int64)
    contact = np.zeros((n_frames, n, n), bool)
    touching = np.zeros((n, n), bool)
    for step in range(n_frames * sub):
        for a, an in enumerate(animals):
            _behave(an, a, animals, rngs[a], social_rng, spaces[a], dt, p_rest, approach)
            b = an.behaviour
            if an.climb >= 0:  # walk on over the other animal
                b = _Behaviour("walk", max(b.timer, 0.5), 90.0 * sizes[a], 0.0)
            elif an.target >= 0 and b.name == "walk":
                b = _steer(an, animals[an.target].pose, b, sizes[a])
            c = clocks[a]
            an.pose = _locomote(an.pose, b, c.step_strength[step], c.freeze, dt, spaces[a])
        touching = _contacts(animals, prints, spaces, touching, social_rng, climb, dt)
        for a, an in enumerate(animals):
            an.head = _move_head(an.head, an.behaviour.name, dt, rngs[a])
            an.feet = _step_feet(an.feet, an.pose, gaits[a], dt)  # type: ignore[arg-type]
            still = an.behaviour.name == "rest"
            an.sway += dt * (0.02 if still else 2.0 + 0.01 * abs(an.pose.v))
            if (step + 1) % sub == 0:
                f = step // sub
                tracks[a].record(f, an.pose, an.head, an.feet, an.sway)  # type: ignore[arg-type]
                on_top[f, a] = an.climb
                contact[f] = touching
    states = tuple(
        motion_state(tr, c, stimulation if a == 0 else None, s, half)
        for a, (tr, c, s) in enumerate(zip(tracks, clocks, sizes))
    )
    lift = _lift(states, prints, on_top, heights, fps)
    return SocialMotion(states, lift, on_top, contact)


def _behave(
    an: _Animal,
    a: int,
    animals: list[_Animal],
    rng: np.random.Generator,
    social_rng: np.random.Generator,
    space: _Space,
    dt: float,
    p_rest: float,
    approach: float,
) -> None:
    """One sub-step of an animal's behaviour; a new walk may head for another animal."""
    before = an.behaviour
    an.behaviour = _next_behaviour(before, dt, space.s, rng, p_rest)
    if an.behaviour.name != "walk":
        an.target = -1
    elif before.name != "walk" or an.behaviour.timer > before.timer:  # a new walk
        others = [i for i in range(len(animals)) if i != a]
        pick = social_rng.random() < approach
        an.target = others[int(social_rng.integers(len(others)))] if pick else -1
        an.aim = float(social_rng.choice([90.0, -110.0, 0.0])) * space.s if pick else 0.0


def _steer(an: _Animal, o: _Pose, b: _Behaviour, s: float) -> _Behaviour:
    """The walk ``b`` turned towards the aimed point of the target at ``o``.

    The target is dropped once the animal's head (about 90 mm ahead of its torso centre
    for a rat) is within 40 mm of that point.
    """
    gx = o.x + an.aim * math.cos(o.yaw)
    gy = o.y + an.aim * math.sin(o.yaw)
    hx = an.pose.x + 90.0 * s * math.cos(an.pose.yaw)
    hy = an.pose.y + 90.0 * s * math.sin(an.pose.yaw)
    if math.hypot(gx - hx, gy - hy) < 40.0 * s:
        an.target = -1
        return b
    steer = 3.0 * _wrap(math.atan2(gy - an.pose.y, gx - an.pose.x) - an.pose.yaw)
    return replace(b, w_noise=float(np.clip(steer, -3.0, 3.0)))


def _contacts(
    animals: list[_Animal],
    prints: list[tuple[np.ndarray, np.ndarray]],
    spaces: list[_Space],
    touching: np.ndarray,
    rng: np.random.Generator,
    p_climb: float,
    dt: float,
) -> np.ndarray:
    """Resolve overlapping prints: start, keep or end climbs, push the others apart.

    Returns:
        (A, A) bool, which pairs touch now.
    """
    n = len(animals)
    now = np.zeros((n, n), bool)
    world = [_world_prints(prints[a][0], an.pose) for a, an in enumerate(animals)]
    for an in animals:
        if an.climb >= 0:
            an.climb_t += dt
    for i in range(n):
        for j in range(i + 1, n):
            gap, v = _gap(world[i], prints[i][1], world[j], prints[j][1])
            ai, aj = animals[i], animals[j]
            climbing = ai.climb == j or aj.climb == i
            if gap > 0:
                for x, y in ((ai, j), (aj, i)):
                    if x.climb == y:
                        x.climb, x.climb_t = -1, 0.0
                continue
            now[i, j] = now[j, i] = True
            if climbing:
                for x, y in ((ai, j), (aj, i)):
                    if x.climb == y and x.climb_t > _CLIMB_MAX_S:
                        x.climb, x.climb_t = -1, 0.0
                if ai.climb == j or aj.climb == i:
                    continue
            elif not touching[i, j] and ai.climb < 0 and aj.climb < 0 and rng.random() < p_climb:
                up = ai if abs(ai.pose.v) >= abs(aj.pose.v) else aj
                up.climb, up.climb_t = (j if up is ai else i), 0.0
                continue
            push = min(-gap / 2, _PUSH_MM)
            ai.pose = _moved(ai.pose, v * push, spaces[i])
            aj.pose = _moved(aj.pose, -v * push, spaces[j])
    return now


def _moved(p: _Pose, d: np.ndarray, space: _Space) -> _Pose:
    """``p`` moved by ``d`` (2,) mm on the floor, kept inside the arena as ``_locomote`` does."""
    lim = space.half - space.margin + 30 * space.s
    x = float(np.clip(p.x + d[0], -lim[0], lim[0]))
    y = float(np.clip(p.y + d[1], -lim[1], lim[1]))
    return replace(p, x=x, y=y)


def _lift(
    states: Sequence[MotionState],
    prints: list[tuple[np.ndarray, np.ndarray]],
    on_top: np.ndarray,
    heights: np.ndarray,
    fps: float,
) -> np.ndarray:
    """(T, A) height each animal is raised: the other's back height times the overlap."""
    T, n = on_top.shape
    lift = np.zeros((T, n))
    for t in range(T):
        for a in range(n):
            b = int(on_top[t, a])
            if b < 0:
                continue
            pa = _Pose(*states[a].root_xy[t], states[a].yaw[t], 0.0, 0.0, 0.0)
            pb = _Pose(*states[b].root_xy[t], states[b].yaw[t], 0.0, 0.0, 0.0)
            wa, wb = _world_prints(prints[a][0], pa), _world_prints(prints[b][0], pb)
            # how far the climber's torso (its mean disc centre) is over the other's print
            d = np.linalg.norm(wb - wa[:2].mean(0), axis=-1) - prints[b][1]
            over = float(np.clip(1.0 - d.min() / (prints[a][1][:2].mean()), 0.0, 1.0))
            lift[t, a] = heights[b] * float(_smoothstep(over * 1.5))
    k = max(1, int(round(0.2 * fps)))
    kernel = np.ones(k) / k
    return np.stack(
        [np.convolve(np.pad(lift[:, a], (k // 2, k - 1 - k // 2), "edge"), kernel, "valid")
         for a in range(n)], axis=1,
    )  # fmt: skip


def combine_geometries(
    geoms: Sequence[BodyGeometry], lift: np.ndarray | None = None
) -> BodyGeometry:
    """One geometry of several animals: parts and keypoints one animal after the other.

    Args:
        geoms: (A,) the animals' geometries over the same T frames.
        lift: (T, A) mm each animal is raised, or None.

    Returns:
        The geometry: (T, A * N, ...) parts, (T, A * 12, 3) keypoints; animal ``a``'s
        materials offset by ``a * len(MATERIALS)`` (rows of :func:`combined_palette`).
    """
    up = np.array([0.0, 0.0, 1.0])
    centers, keypoints = [], []
    for a, g in enumerate(geoms):
        dz = 0.0 if lift is None else lift[:, a, None, None] * up
        centers.append(g.centers + dz)
        keypoints.append(g.keypoints + dz)
    return BodyGeometry(
        np.concatenate(centers, axis=1),
        np.concatenate([g.axes for g in geoms], axis=1),
        np.concatenate([g.radii for g in geoms], axis=1),
        np.concatenate(keypoints, axis=1),
        np.concatenate([g.materials + a * len(MATERIALS) for a, g in enumerate(geoms)]),
    )


def combined_palette(bodies: Sequence[RatBody]) -> np.ndarray:
    """(A * M, 2, 3) the animals' palettes one after the other (see :func:`combine_geometries`)."""
    return np.concatenate([b.palette for b in bodies], axis=0)


__all__ = [
    "MAX_ANIMALS",
    "SocialMotion",
    "combine_geometries",
    "combined_palette",
    "simulate_social",
]
