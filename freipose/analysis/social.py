"""Social variables of several animals, and per-animal variables that include them.

Poses are ``(time, animal, keypoint, xyz)`` arrays. For every ordered pair of animals
(``a`` looks at ``b``) the variables are:

======================  =====  =============================================================
kind                    unit   meaning
======================  =====  =============================================================
``social_dist``         mm     distance between a body point of ``a`` and one of ``b``: the
                               head (the skeleton's ``[frame]`` origin) to ``b``'s head, to
                               ``b``'s ``toward`` point (the tail base: sniffing), and the
                               body centres (mean of all keypoints); plus ``pairs`` given
``social_min_dist``     mm     closest distance between any keypoint of ``a`` and any of ``b``
``social_approach``     mm/s   time derivative of the centres' distance (< 0: closing in)
``facing``              deg    horizontal angle between ``a``'s heading (from its ``toward``
                               point to its head) and the direction from ``a``'s head to
                               ``b``'s centre: 0 = ``a`` faces ``b``, 180 = turned away
``contact``             0/1    ``social_min_dist`` below ``contact_mm``
======================  =====  =============================================================

A variable's part names the two body points and the other animal, e.g.
``social_dist[head-tail of animal 1]``, ``facing[animal 1]``. :func:`animal_variables` gives
one animal's :class:`~freipose.analysis.variables.Variables` (its own body variables, then
its social variables towards every other animal), so attribution (``freipose analyze``)
runs per animal on several animals' poses as it does on one.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from freipose.analysis.floor import FloorPlane
from freipose.analysis.signals import time_derivative
from freipose.analysis.variables import (
    VariableConfig,
    Variables,
    VariablesError,
    compute_variables,
    prepare_poses,
)
from freipose.skeleton import Skeleton

SOCIAL_UNITS = {
    "social_dist": "mm",
    "social_min_dist": "mm",
    "social_approach": "mm/s",
    "facing": "deg",
    "contact": "",
}


@dataclass(frozen=True)
class SocialConfig:
    """Settings of the social variables.

    Attributes:
        contact_mm: closest keypoint distance below which two animals touch.
        pairs: extra (keypoint of a, keypoint of b) distances, by keypoint name.
    """

    contact_mm: float = 15.0
    pairs: tuple[tuple[str, str], ...] = ()

    def __post_init__(self) -> None:
        if not (np.isfinite(self.contact_mm) and self.contact_mm > 0):
            raise VariablesError(f"contact_mm must be positive, got {self.contact_mm}")


@dataclass(frozen=True, eq=False)
class SocialVariables:
    """Social variables of animal ``a`` towards the others.

    Attributes:
        values: (T, V) float32.
        names, kinds, parts: (V,) as in :class:`~freipose.analysis.variables.Variables`.
        involved: (V, K) bool, the keypoints of animal ``a`` each variable uses.
    """

    values: np.ndarray
    names: tuple[str, ...]
    kinds: tuple[str, ...]
    parts: tuple[str, ...]
    involved: np.ndarray


def _check(poses: np.ndarray, skeleton: Skeleton) -> np.ndarray:
    p = np.asarray(poses, dtype=np.float64)
    if p.ndim != 4 or p.shape[2:] != (skeleton.num_keypoints, 3):
        raise VariablesError(
            f"poses of several animals must be (T, A, {skeleton.num_keypoints}, 3) for skeleton "
            f"{skeleton.name!r}, got {p.shape}"
        )
    if p.shape[1] < 2:
        raise VariablesError(f"social variables need at least 2 animals, got {p.shape[1]}")
    if "origin" not in skeleton.frame or "toward" not in skeleton.frame:
        raise VariablesError(
            f"skeleton {skeleton.name!r} defines no body frame ([frame] origin and toward), "
            "which gives the head and the heading of the social variables"
        )
    return p


def _horizontal(v: np.ndarray, up: np.ndarray) -> np.ndarray:
    return v - (v @ up)[..., None] * up


def social_variables(
    poses: np.ndarray,
    skeleton: Skeleton,
    fps: float,
    animal: int,
    up: Sequence[float] = (0.0, 0.0, 1.0),
    config: SocialConfig | None = None,
    individuals: Sequence[str] | None = None,
) -> SocialVariables:
    """The social variables of ``animal`` towards every other animal (module docstring).

    Args:
        poses: (T, A, K, 3) world mm, NaN = missing; a regular time axis.
        skeleton: the keypoints and body frame (``origin``: head, ``toward``: tail base).
        fps: frames per second (for ``social_approach``).
        animal: index of the animal ``a``.
        up: (3,) the up direction.
        config: contact threshold and extra keypoint pairs.
        individuals: (A,) the animals' names in the parts (default ``animal <index>``).

    Returns:
        :class:`SocialVariables` with (A - 1) x (4 + len(pairs)) + ... columns.
    """
    cfg = config or SocialConfig()
    p = _check(poses, skeleton)
    t, n, k, _ = p.shape
    if not 0 <= animal < n:
        raise VariablesError(f"animal must be in 0..{n - 1}, got {animal}")
    u = np.asarray(up, dtype=np.float64)
    u = u / np.linalg.norm(u)
    head_i, tail_i = list(skeleton.frame["origin"]), list(skeleton.frame["toward"])
    idx = {name: i for i, name in enumerate(skeleton.keypoints)}
    for pair in cfg.pairs:
        for name in pair:
            if name not in idx:
                raise VariablesError(
                    f"social pair {pair}: no keypoint {name!r} in {skeleton.name!r}"
                )
    head = p[:, :, head_i].mean(2)  # (T, A, 3)
    tail = p[:, :, tail_i].mean(2)
    centre = p.mean(2)
    cols: list[np.ndarray] = []
    names: list[str] = []
    kinds: list[str] = []
    parts: list[str] = []
    inv: list[np.ndarray] = []
    every = np.ones(k, bool)
    head_m, tail_m = np.isin(np.arange(k), head_i), np.isin(np.arange(k), tail_i)

    def add(kind: str, part: str, col: np.ndarray, used: np.ndarray) -> None:
        cols.append(col)
        kinds.append(kind)
        parts.append(part)
        names.append(f"{kind}[{part}]")
        inv.append(used)

    a = animal
    for b in range(n):
        if b == a:
            continue
        other = f"animal {b}" if individuals is None else str(individuals[b])
        hh = np.linalg.norm(head[:, a] - head[:, b], axis=-1)
        add("social_dist", f"head-head of {other}", hh, head_m)
        add(
            "social_dist",
            f"head-tail of {other}",
            np.linalg.norm(head[:, a] - tail[:, b], axis=-1),
            head_m,
        )
        cdist = np.linalg.norm(centre[:, a] - centre[:, b], axis=-1)
        add("social_dist", f"centre-centre of {other}", cdist, every)
        for ka, kb in cfg.pairs:
            d = np.linalg.norm(p[:, a, idx[ka]] - p[:, b, idx[kb]], axis=-1)
            add("social_dist", f"{ka}-{kb} of {other}", d, np.arange(k) == idx[ka])
        md = np.linalg.norm(p[:, a, :, None] - p[:, b, None, :], axis=-1)  # (T, K, K)
        with np.errstate(invalid="ignore"):
            mind = np.where(
                np.isfinite(md).any((1, 2)),
                np.nanmin(np.where(np.isfinite(md), md, np.inf), (1, 2)),
                np.nan,
            )
        add("social_min_dist", other, mind, every)
        add("social_approach", other, time_derivative(cdist, fps), every)
        heading = _horizontal(head[:, a] - tail[:, a], u)
        towards = _horizontal(centre[:, b] - head[:, a], u)
        cr = np.linalg.norm(np.cross(heading, towards), axis=-1)
        dot = np.einsum("ti,ti->t", heading, towards)
        add("facing", other, np.degrees(np.arctan2(cr, dot)), head_m | tail_m)
        with np.errstate(invalid="ignore"):
            add(
                "contact",
                other,
                np.where(np.isfinite(mind), (mind < cfg.contact_mm) * 1.0, np.nan),
                every,
            )
    values = np.stack(cols, axis=1).astype(np.float32) if cols else np.zeros((t, 0), np.float32)
    return SocialVariables(values, tuple(names), tuple(kinds), tuple(parts), np.asarray(inv, bool))


def animal_variables(
    poses: np.ndarray,
    frame_index: np.ndarray,
    fps: float,
    skeleton: Skeleton,
    floor: FloorPlane,
    animal: int,
    config: VariableConfig = VariableConfig(),
    social: SocialConfig | None = None,
    individuals: Sequence[str] | None = None,
) -> Variables:
    """One animal's variables: its body variables, then its social variables.

    Args:
        poses: (T, A, K, 3) world mm, NaN = missing, several animals.
        frame_index: (T,) strictly increasing video frames.
        fps: frames per second.
        skeleton: keypoints, body frame and angles.
        floor: the floor plane (its normal is up).
        animal: which animal.
        config: gap filling and STFT settings (as for one animal).
        social: contact threshold and extra keypoint pairs.
        individuals: (A,) the animals' names (see :func:`social_variables`).

    Returns:
        :class:`~freipose.analysis.variables.Variables` of the animal, the social variables
        appended (component ``""``; ``info["animal"]`` names the animal).
    """
    p = _check(poses, skeleton)
    if not 0 <= animal < p.shape[1]:
        raise VariablesError(f"animal must be in 0..{p.shape[1] - 1}, got {animal}")
    own = compute_variables(p[:, animal], frame_index, fps, skeleton, floor, config)
    filled = np.stack(
        [
            prepare_poses(p[:, b], frame_index, fps, skeleton, config).poses
            for b in range(p.shape[1])
        ],
        axis=1,
    )
    soc = social_variables(filled, skeleton, fps, animal, floor.normal, social, individuals)
    return Variables(
        values=np.concatenate([own.values, soc.values], axis=1),
        names=own.names + soc.names,
        kinds=own.kinds + soc.kinds,
        components=own.components + ("",) * len(soc.names),
        parts=own.parts + soc.parts,
        involved=np.concatenate([own.involved, soc.involved], axis=0),
        keypoints=own.keypoints,
        frame_index=own.frame_index,
        fps=own.fps,
        frequencies=own.frequencies,
        floor=own.floor,
        info={**own.info, "animal": int(animal), "animals": int(p.shape[1])},
    )


def recording_variables(
    poses: np.ndarray,
    individuals: Sequence[str],
    frame_index: np.ndarray,
    fps: float,
    skeleton: Skeleton,
    floor: FloorPlane,
    config: VariableConfig = VariableConfig(),
    social: SocialConfig | None = None,
) -> Variables:
    """The variables of every animal of a recording, in one table.

    Each animal's :func:`animal_variables` (its body variables, then its social variables
    towards the others, named by the others' ``individuals``), its variables' names
    prefixed with its name: ``animal_0/local_z[Nose]``,
    ``animal_0/social_dist[head-head of animal_1]``. The parts stay the keypoint or angle
    (the social ones name the other animal).

    Args:
        poses: (T, A, K, 3) world mm, NaN = missing, A >= 2.
        individuals: (A,) the animals' names.
        frame_index: (T,) strictly increasing video frames.
        fps: frames per second.
        skeleton: keypoints, body frame and angles.
        floor: the floor plane (its normal is up).
        config: gap filling and STFT settings.
        social: contact threshold and extra keypoint pairs.

    Returns:
        :class:`~freipose.analysis.variables.Variables` with the A animals' columns, in
        order; ``info`` sums the keypoints missing and interpolated over the animals, counts
        the frames with any undefined variable, and lists ``individuals``.
    """
    names = [str(n) for n in individuals]
    p = _check(poses, skeleton)
    if len(names) != p.shape[1]:
        raise VariablesError(f"{len(names)} individuals for poses of {p.shape[1]} animals")
    per = [
        animal_variables(p, frame_index, fps, skeleton, floor, a, config, social, names)
        for a in range(len(names))
    ]
    first = per[0]
    values = np.concatenate([v.values for v in per], axis=1)
    info = dict(first.info)
    for key in ("keypoints_missing", "keypoints_interpolated"):
        info[key] = int(sum(int(v.info[key]) for v in per))
    info.pop("animal", None)
    info["frames_with_nan"] = int(np.isnan(values).any(axis=1).sum())
    info["individuals"] = names
    return Variables(
        values=values,
        names=tuple(f"{n}/{v}" for n, var in zip(names, per, strict=True) for v in var.names),
        kinds=tuple(k for v in per for k in v.kinds),
        components=tuple(c for v in per for c in v.components),
        parts=tuple(x for v in per for x in v.parts),
        involved=np.concatenate([v.involved for v in per], axis=0),
        keypoints=first.keypoints,
        frame_index=first.frame_index,
        fps=first.fps,
        frequencies=first.frequencies,
        floor=first.floor,
        info=info,
    )
