"""The articulated synthetic rodent: ellipsoid body parts and the 12 rat keypoints.

A :class:`RatBody` holds the animal's dimensions (mm) and appearance; :func:`build_body`
turns a :class:`~freipose.synth.state.MotionState` into per-frame ellipsoids
(:class:`BodyGeometry`) and the exact 3D keypoints in the rat skeleton's order. The
keypoints are points of the model itself (the snout tip, eye centres on the head surface,
ear centres, paw centres, ankle joints, toe tips, the tail root on the rump), so their
projections are exactly where the rendered features are.

Body frame: x forward, y left, z up; the world is z up with the floor at z = 0.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import cast

import numpy as np
from numpy.typing import ArrayLike

from freipose.synth.coats import FURRY, MAT, coat_palette
from freipose.synth.errors import SynthError
from freipose.synth.state import MotionState

RAT_KEYPOINTS = (
    "Ear Right", "Eye Right", "Paw Front Right", "Paw Back Right Ankle", "Paw Back Right Tip",
    "Ear Left", "Eye Left", "Paw Front Left", "Paw Back Left Ankle", "Paw Back Left Tip",
    "Nose", "Tail",
)  # fmt: skip

N_TAIL = 10

# Part names, in render order (index = part id).
PART_NAMES: tuple[str, ...] = (
    "haunch", "chest", "neck", "head", "snout", "nose", "eye_r", "eye_l", "ear_r", "ear_l",
    "upper_arm_r", "upper_arm_l", "forearm_r", "forearm_l", "paw_front_r", "paw_front_l",
    "thigh_r", "thigh_l", "shin_r", "shin_l", "foot_r", "foot_l",
) + tuple(f"tail_{i}" for i in range(N_TAIL))  # fmt: skip
PART: Mapping[str, int] = MappingProxyType({n: i for i, n in enumerate(PART_NAMES)})


def per_animal_parts(parts: tuple[int, ...], n_parts: int) -> np.ndarray:
    """The ids of ``parts`` of one animal in every animal of a geometry of ``n_parts`` parts.

    A geometry of several animals (``freipose.synth.social.combine_geometries``) holds
    their parts one animal after the other: animal ``a``'s part ``i`` is ``i + a * N``.
    """
    one = np.asarray(parts, dtype=np.int64)
    return np.concatenate([one + a * len(PART_NAMES) for a in range(n_parts // len(PART_NAMES))])


# Material of each part (index into the coat's palette, freipose.synth.coats.MATERIALS).
PART_MATERIAL = np.array(
    [MAT[m] for m in (
        "haunch", "chest", "head", "head", "snout", "nose", "eye", "eye", "ear", "ear",
        "limb", "limb", "limb", "limb", "paw", "paw",
        "limb", "limb", "limb", "limb", "paw", "paw",
    )] + [MAT["tail"]] * N_TAIL,
    dtype=np.int64,
)  # fmt: skip
PART_MATERIAL.setflags(write=False)
#: the piebald coat's materials: every furry part white with dark patches (``"patched"``)
PIEBALD_MATERIAL = np.where(np.isin(PART_MATERIAL, FURRY), MAT["patched"], PART_MATERIAL)
PIEBALD_MATERIAL.setflags(write=False)

# Parts a keypoint belongs to (ignored when testing whether the keypoint is occluded).
KEYPOINT_OWNERS: tuple[tuple[int, ...], ...] = (
    (PART["ear_r"],),
    (PART["eye_r"],),
    (PART["forearm_r"], PART["paw_front_r"]),
    (PART["shin_r"], PART["foot_r"]),
    (PART["foot_r"],),
    (PART["ear_l"],),
    (PART["eye_l"],),
    (PART["forearm_l"], PART["paw_front_l"]),
    (PART["shin_l"], PART["foot_l"]),
    (PART["foot_l"],),
    (PART["nose"], PART["snout"]),
    (PART["tail_0"],),
)

APPEARANCES = ("hooded", "albino")  # the coats ``appearance = "random"`` draws for a rat
#: every coat ("dark": a black mouse or rat; "piebald": white with irregular dark patches,
#: drawn neither by ``appearance = "random"`` nor by ``randomize``, so the shipped base
#: models never saw it: a coat outside their training data)
COATS = (*APPEARANCES, "dark", "piebald")
MOUSE_COATS = ("dark", "albino")  # the coats ``appearance = "random"`` draws for a mouse


@dataclass(frozen=True)
class RatBody:
    """Dimensions (mm, before ``scale``) and appearance of one synthetic rat.

    Attributes:
        scale: overall size factor (1.0 = an adult rat of ~23 cm nose to tail root).
        length: extra factor on the torso length.
        girth: extra factor on the torso width and height.
        tail_length: extra factor on the tail length.
        appearance: ``"hooded"`` (black head and back stripe, white belly and flanks),
            ``"albino"`` (white with pink ears, eyes, paws and tail), ``"dark"`` (black
            fur, grey-pink ears, paws and tail) or ``"piebald"`` (white fur with irregular
            black patches on the torso, head and legs; pink paws, grey ears and tail;
            never drawn at random, see :data:`COATS`).
        tint: (3,) BGR multiplier on the fur colour (small individual differences).
    """

    scale: float = 1.0
    length: float = 1.0
    girth: float = 1.0
    tail_length: float = 1.0
    appearance: str = "hooded"
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def __post_init__(self) -> None:
        if self.appearance not in COATS:
            raise SynthError(f"appearance must be one of {COATS}, got {self.appearance!r}")
        for name in ("scale", "length", "girth", "tail_length"):
            v = float(getattr(self, name))
            if not (0.3 <= v <= 3.0):
                raise SynthError(f"RatBody.{name} must be in [0.3, 3], got {v}")

    @classmethod
    def random(
        cls,
        rng: np.random.Generator,
        appearance: str = "random",
        size: float = 1.0,
        coats: tuple[str, ...] = APPEARANCES,
    ) -> RatBody:
        """A random individual: size ``size`` +-12 %, proportions +-5 %.

        Args:
            rng: the random generator.
            appearance: the coat, or ``"random"``: one of ``coats``.
            size: nominal size factor (rat 1, mouse 0.42).
            coats: the coats a random appearance is drawn from.
        """
        if appearance == "random":
            appearance = coats[int(rng.integers(len(coats)))]
        return cls(
            scale=float(size) * float(rng.uniform(0.88, 1.12)),
            length=float(rng.uniform(0.95, 1.05)),
            girth=float(rng.uniform(0.94, 1.06)),
            tail_length=float(rng.uniform(0.9, 1.1)),
            appearance=appearance,
            tint=cast(
                "tuple[float, float, float]",
                tuple(float(v) for v in rng.uniform(0.94, 1.0, size=3)),
            ),
        )

    @property
    def palette(self) -> np.ndarray:
        """(n_materials, 2, 3) BGR albedo in [0, 1] of this coat (:func:`coat_palette`)."""
        return coat_palette(self.appearance, self.tint)


@dataclass(frozen=True, eq=False)
class BodyGeometry:
    """Ellipsoids of the animal over T frames and its keypoints.

    Attributes:
        centers: (T, N, 3) ellipsoid centres, world mm.
        axes: (T, N, 3, 3) rotation whose columns are the ellipsoid's local axes in world.
        radii: (T, N, 3) semi-axes along those local axes, mm.
        keypoints: (T, 12, 3) world mm, rat skeleton order.
        materials: (N,) material index per part.
    """

    centers: np.ndarray
    axes: np.ndarray
    radii: np.ndarray
    keypoints: np.ndarray
    materials: np.ndarray = field(default_factory=lambda: PART_MATERIAL.copy())

    def __len__(self) -> int:
        return self.centers.shape[0]

    def bounding_radius(self) -> np.ndarray:
        """(T, N) radius of each part's bounding sphere."""
        return self.radii.max(axis=-1)

    def lowest_z(self) -> np.ndarray:
        """(T, N) lowest z of each ellipsoid (support function along -z)."""
        return self.centers[..., 2] - np.sqrt(
            np.sum((self.axes[..., 2, :] * self.radii) ** 2, axis=-1)
        )


# -- small vectorized rotation helpers (leading axes broadcast) -----------------------------


def rot_z(a: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation about z by ``a`` radians."""
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack(
        [np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2
    )


def rot_y(a: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation about y by ``a`` radians."""
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack(
        [np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2
    )


def rot_x(a: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation about x by ``a`` radians."""
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack(
        [np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2
    )


def _apply(R: np.ndarray, v: np.ndarray) -> np.ndarray:
    """R (..., 3, 3) times vectors v (..., 3) or (3,)."""
    return np.einsum("...ij,...j->...i", R, np.broadcast_to(v, R.shape[:-1]))


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, 1e-12)


def segment_ellipsoid(
    p: np.ndarray, q: np.ndarray, radius: float | np.ndarray, overlap: float = 0.5
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An elongated ellipsoid covering the segment p→q (..., 3) with the given radius.

    Returns ``(center (..., 3), axes (..., 3, 3), radii (..., 3))``; the long axis extends
    ``overlap * radius`` beyond each end so that chained segments join smoothly.
    """
    d = q - p
    length = np.linalg.norm(d, axis=-1)
    u = _unit(d)
    ref = np.where(np.abs(u[..., 2:3]) < 0.9, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    v = _unit(np.cross(ref, u))
    w = np.cross(u, v)
    axes = np.stack([u, v, w], axis=-1)
    r = np.broadcast_to(np.asarray(radius, dtype=np.float64), length.shape)
    radii = np.stack([length / 2 + overlap * r, r, r], axis=-1)
    return (p + q) / 2, axes, radii


def two_link_ik(a: np.ndarray, c: np.ndarray, l1: float, l2: float, hint: np.ndarray) -> np.ndarray:
    """Middle joint (..., 3) of a two-segment limb from ``a`` to ``c`` bending towards ``hint``."""
    d = c - a
    dist = np.linalg.norm(d, axis=-1, keepdims=True)
    u = d / np.maximum(dist, 1e-9)
    L = np.clip(dist, abs(l1 - l2) + 1e-6, l1 + l2 - 1e-6)
    along = (L**2 + l1**2 - l2**2) / (2 * L)
    h = np.sqrt(np.maximum(l1**2 - along**2, 0.0))
    perp = _unit(hint - np.sum(hint * u, axis=-1, keepdims=True) * u)
    return a + u * along + perp * h


def _surface_point(center: np.ndarray, radii: np.ndarray, direction: ArrayLike) -> np.ndarray:
    """Point of an axis-aligned ellipsoid surface in ``direction`` (unit-sphere direction)."""
    dirn = np.asarray(direction, dtype=np.float64)
    dirn = dirn / np.linalg.norm(dirn)
    return np.asarray(center, dtype=np.float64) + np.asarray(radii) * dirn


# -- the builder ---------------------------------------------------------------------------


class _Dims:
    """Body-frame dimensions of a :class:`RatBody` in mm."""

    def __init__(self, b: RatBody) -> None:
        s, L, G = b.scale, b.scale * b.length, b.scale * b.girth
        self.s = s
        self.pivot = np.array([-50 * L, 0, 16 * G])
        self.haunch_c = np.array([-32 * L, 0, 40 * G])
        self.haunch_r = np.array([60 * L, 35 * G, 31 * G])
        self.chest_c = np.array([20 * L, 0, 43 * G])
        self.chest_r = np.array([54 * L, 28 * G, 27 * G])
        self.bend = np.array([0.0, 0, 40 * G])
        self.neck = np.array([70 * L, 0, 50 * G])
        self.neck_r = np.array([17, 18, 17]) * G
        # head frame (origin at the neck point)
        self.head_c = np.array([24.0, 0, 2]) * s
        self.head_r = np.array([27.0, 17, 16]) * s
        self.snout_c = np.array([50.0, 0, -3]) * s
        self.snout_r = np.array([16.0, 9.5, 8.5]) * s
        self.nose_tip = self.snout_c + np.array([self.snout_r[0], 0, 0])
        self.nose_c = self.nose_tip - np.array([2.2, 0, -0.6]) * s
        self.nose_radius = 3.0 * s
        self.eye = [
            _surface_point(self.head_c, self.head_r, [0.5, sgn * 0.62, 0.5]) for sgn in (-1, 1)
        ]
        self.eye_radius = 3.6 * s
        self.ear = [np.array([6.0, sgn * 13.5, 17.5]) * s for sgn in (-1, 1)]
        self.ear_r = np.array([2.0, 8.5, 9.5]) * s
        # limbs (torso frame)
        self.shoulder = [np.array([40 * L, sgn * 15 * G, 32 * G]) for sgn in (-1, 1)]
        self.arm = (26 * s, 30 * s)
        self.arm_radius = (7.0 * s, 5.0 * s)
        self.paw_r = np.array([9.0, 5.5, 4.0]) * s
        self.hip = [np.array([-45 * L, sgn * 22 * G, 32 * G]) for sgn in (-1, 1)]
        self.leg = (36 * s, 40 * s)
        self.leg_radius = (11.0 * s, 6.0 * s)
        self.foot_len = 36 * s
        self.foot_width = 6.0 * s
        self.foot_height = 4.0 * s
        # tail root on the rump surface, tail segments
        self.tail_root = _surface_point(self.haunch_c, self.haunch_r, [-1.0, 0, -0.12])
        self.tail_seg = 19.0 * s * b.tail_length
        self.tail_radius = np.linspace(5.5, 1.8, N_TAIL) * s
        # rest positions of the feet (torso frame, floor heights)
        self.front_paw_rest = [np.array([44 * L, sgn * 16 * G, 4.5 * s]) for sgn in (-1, 1)]
        self.hind_tip_rest = [np.array([-18 * L, sgn * 27 * G, 2.5 * s]) for sgn in (-1, 1)]
        self.rear_paw = [np.array([52 * L, sgn * 12 * G, 8 * G]) for sgn in (-1, 1)]


def body_dims(body: RatBody) -> _Dims:
    """The body-frame dimensions of ``body`` (used by the motion model for foot placement)."""
    return _Dims(body)


# A placed part: centre (T, 3), axes (T, 3, 3) (columns: local axes in world) and radii
# ((3,) or (T, 3)), mm.
_Part = tuple[np.ndarray, np.ndarray, np.ndarray]


@dataclass(frozen=True, eq=False)
class _Frames:
    """The torso's and head's joints and rotations over T frames (lifted off the floor).

    Attributes:
        Ryaw: (T, 3, 3) heading rotation.
        Rt: (T, 3, 3) haunch (heading and pitch).
        Rc: (T, 3, 3) chest (haunch and bend).
        Rh: (T, 3, 3) head (chest and head yaw, pitch, roll).
        P: (T, 3) haunch pivot, mm.
        B: (T, 3) bend point between haunch and chest, mm.
        N: (T, 3) neck point (origin of the head frame), mm.
        fwd: (T, 3) the heading's forward direction.
    """

    Ryaw: np.ndarray
    Rt: np.ndarray
    Rc: np.ndarray
    Rh: np.ndarray
    P: np.ndarray
    B: np.ndarray
    N: np.ndarray
    fwd: np.ndarray


def _body_frames(D: _Dims, state: MotionState, floor_clearance: float) -> _Frames:
    """Chain heading, pitch, bend and head angles; lift the upper body off the floor.

    The torso and head are lifted so that none of their ellipsoids comes closer than
    ``floor_clearance`` mm to the floor (deep rearing, head down).
    """
    T = len(state.yaw)
    root = np.concatenate([state.root_xy, np.zeros((T, 1))], axis=1)
    Ryaw = rot_z(state.yaw)
    pitch = state.pitch
    Rt = Ryaw @ rot_y(-pitch)
    P = root + _apply(Ryaw, D.pivot)
    B = P + _apply(Rt, D.bend - D.pivot)
    Rc = Rt @ rot_z(state.bend)
    N = B + _apply(Rc, D.neck - D.bend)
    Rh = Rc @ rot_z(state.head_yaw) @ rot_y(-state.head_pitch) @ rot_x(state.head_roll)

    def lowest(c: np.ndarray, R: np.ndarray, r: np.ndarray) -> np.ndarray:
        return c[:, 2] - np.sqrt(np.sum((R[:, 2, :] * r) ** 2, axis=-1))

    low = np.minimum.reduce([
        lowest(P + _apply(Rt, D.haunch_c - D.pivot), Rt, D.haunch_r),
        lowest(B + _apply(Rc, D.chest_c - D.bend), Rc, D.chest_r),
        lowest(N + _apply(Rh, D.head_c), Rh, D.head_r),
        lowest(N + _apply(Rh, D.snout_c), Rh, D.snout_r),
    ])  # fmt: skip
    lift = np.maximum(0.0, floor_clearance - low)[:, None] * np.array([0.0, 0, 1])
    fwd = _apply(Ryaw, np.array([1.0, 0, 0]))
    return _Frames(Ryaw, Rt, Rc, Rh, P + lift, B + lift, N + lift, fwd)


@dataclass(frozen=True, eq=False)
class _TorsoHead:
    """The torso and head parts and their keypoints.

    Attributes:
        parts: part name -> placed part.
        eyes: (right, left) eye centres, (T, 3) each.
        ears: (right, left) ear centres, (T, 3) each.
        nose_tip: (T, 3) the snout tip.
    """

    parts: dict[str, _Part]
    eyes: tuple[np.ndarray, np.ndarray]
    ears: tuple[np.ndarray, np.ndarray]
    nose_tip: np.ndarray


def _torso_and_head(D: _Dims, fr: _Frames) -> _TorsoHead:
    """Haunch, chest, neck, head, snout, nose, eyes and ears."""
    P, B, N, Rt, Rc, Rh = fr.P, fr.B, fr.N, fr.Rt, fr.Rc, fr.Rh
    T = len(P)
    parts: dict[str, _Part] = {
        "haunch": (P + _apply(Rt, D.haunch_c - D.pivot), Rt, D.haunch_r),
        "chest": (B + _apply(Rc, D.chest_c - D.bend), Rc, D.chest_r),
        "neck": (N, Rh, D.neck_r),
        "head": (N + _apply(Rh, D.head_c), Rh, D.head_r),
        "snout": (N + _apply(Rh, D.snout_c), Rh, D.snout_r),
        "nose": (N + _apply(Rh, D.nose_c), Rh, np.full(3, D.nose_radius)),
    }
    eyes = [N + _apply(Rh, e) for e in D.eye]
    ears = [N + _apply(Rh, e) for e in D.ear]
    for side, sgn, k in (("r", -1, 0), ("l", 1, 1)):
        parts[f"eye_{side}"] = (eyes[k], Rh, np.full(3, D.eye_radius))
        ear_rot = Rh @ rot_z(np.full(T, sgn * 0.6)) @ rot_x(np.full(T, sgn * 0.35))
        parts[f"ear_{side}"] = (ears[k], ear_rot, D.ear_r)
    nose_tip = N + _apply(Rh, D.nose_tip)
    return _TorsoHead(parts, (eyes[0], eyes[1]), (ears[0], ears[1]), nose_tip)


@dataclass(frozen=True, eq=False)
class _FrontLegs:
    """Upper arms, forearms and front paws, and the paw centres (T, 2, 3) (right, left)."""

    parts: dict[str, _Part]
    paws: np.ndarray


def _front_legs(D: _Dims, fr: _Frames, state: MotionState) -> _FrontLegs:
    """Front legs from the shoulders to the paws (on the floor, or at the chest when rearing)."""
    B, Rc, fwd = fr.B, fr.Rc, fr.fwd
    w = state.rear_weight[:, None]
    paws = np.zeros((len(B), 2, 3))
    parts: dict[str, _Part] = {}
    for side, k in (("r", 0), ("l", 1)):
        sh = B + _apply(Rc, D.shoulder[k] - D.bend)
        floor_paw = state.feet[:, k] + state.foot_offsets[:, k]
        chest_paw = B + _apply(Rc, D.rear_paw[k] - D.bend) + state.foot_offsets[:, k]
        paw = (1 - w) * floor_paw + w * chest_paw
        paw[:, 2] = np.maximum(paw[:, 2], D.paw_r[2] + 0.3)
        paws[:, k] = paw
        elbow = two_link_ik(sh, paw, *D.arm, hint=-fwd + np.array([0, 0, 0.2]))
        parts[f"upper_arm_{side}"] = segment_ellipsoid(sh, elbow, D.arm_radius[0])
        parts[f"forearm_{side}"] = segment_ellipsoid(elbow, paw, D.arm_radius[1])
        paw_dir = _unit(fwd + np.array([0, 0, 0.0]))
        v = _unit(np.cross([0.0, 0, 1], paw_dir))
        parts[f"paw_front_{side}"] = (
            paw, np.stack([paw_dir, v, np.cross(paw_dir, v)], -1), D.paw_r
        )  # fmt: skip
    return _FrontLegs(parts, paws)


@dataclass(frozen=True, eq=False)
class _HindLegs:
    """Thighs, shins and feet, the ankles and the toe tips (T, 2, 3) (right, left)."""

    parts: dict[str, _Part]
    ankles: np.ndarray
    tips: np.ndarray


def _hind_legs(D: _Dims, fr: _Frames, state: MotionState) -> _HindLegs:
    """Hind legs from the hips to the toe tips, the heels raised by ``state.heel_angle``."""
    P, Rt, fwd = fr.P, fr.Rt, fr.fwd
    T = len(P)
    ankles = np.zeros((T, 2, 3))
    tips = np.zeros((T, 2, 3))
    parts: dict[str, _Part] = {}
    for side, k in (("r", 0), ("l", 1)):
        hip = P + _apply(Rt, D.hip[k] - D.pivot)
        tip = state.feet[:, 2 + k] + state.foot_offsets[:, 2 + k]
        ang = state.heel_angle[:, k]
        fdir = np.stack([np.cos(state.foot_yaw[:, k]), np.sin(state.foot_yaw[:, k])], -1)
        ankle = tip.copy()
        ankle[:, :2] -= fdir * (D.foot_len * np.cos(ang))[:, None]
        ankle[:, 2] += D.foot_len * np.sin(ang)
        knee = two_link_ik(hip, ankle, *D.leg, hint=fwd + np.array([0, 0, 0.3]))
        knee[:, 2] = np.maximum(knee[:, 2], D.leg_radius[0] + 1.0)
        parts[f"thigh_{side}"] = segment_ellipsoid(hip, knee, D.leg_radius[0], overlap=0.3)
        parts[f"shin_{side}"] = segment_ellipsoid(knee, ankle, D.leg_radius[1])
        u = _unit(tip - ankle)
        v = _unit(np.cross([0.0, 0, 1], u))
        ax = np.stack([u, v, np.cross(u, v)], -1)
        half = np.linalg.norm(tip - ankle, axis=-1) / 2
        rad = np.stack([half, np.full(T, D.foot_width), np.full(T, D.foot_height)], -1)
        parts[f"foot_{side}"] = ((tip + ankle) / 2, ax, rad)
        ankles[:, k], tips[:, k] = ankle, tip
    return _HindLegs(parts, ankles, tips)


@dataclass(frozen=True, eq=False)
class _Tail:
    """The tail segments and the tail root on the rump (T, 3)."""

    parts: dict[str, _Part]
    root: np.ndarray


def _tail(D: _Dims, fr: _Frames, state: MotionState) -> _Tail:
    """The tail: from the rump, down to the floor, then trailing with a sway.

    Its points stay above the floor and, with ``state.arena_half``, inside the arena.
    """
    P, Rt = fr.P, fr.Rt
    root_pt = P + _apply(Rt, D.tail_root - D.pivot)
    pts = [root_pt]
    back = -_apply(Rt, np.array([1.0, 0, 0]))
    heading = np.arctan2(back[:, 1], back[:, 0])
    elev = np.arcsin(np.clip(back[:, 2], -1, 1)) - 0.55
    for i in range(N_TAIL):
        sway = state.tail_sway[:, 0] * np.sin(state.tail_sway[:, 1] + 0.7 * i) * (i + 1) / N_TAIL
        heading = heading + state.tail_curl / N_TAIL + 0.12 * sway
        elev = elev * 0.55
        d = np.stack(
            [np.cos(heading) * np.cos(elev), np.sin(heading) * np.cos(elev), np.sin(elev)], -1
        )
        nxt = pts[-1] + D.tail_seg * d
        nxt[:, 2] = np.maximum(nxt[:, 2], D.tail_radius[i] + 0.3)
        if state.arena_half is not None:
            lim = np.asarray(state.arena_half) - D.tail_radius[i] - 1.0
            nxt[:, :2] = np.clip(nxt[:, :2], -lim, lim)
        pts.append(nxt)
    parts: dict[str, _Part] = {}
    for i in range(N_TAIL):
        c, ax, r = segment_ellipsoid(pts[i], pts[i + 1], D.tail_radius[i], overlap=0.9)
        low = c[:, 2] - np.sqrt(np.sum((ax[:, 2, :] * r) ** 2, axis=-1))
        c[:, 2] += np.maximum(0.0, 0.2 - low)  # a sloping segment's rounded end stays up
        parts[f"tail_{i}"] = (c, ax, r)
    return _Tail(parts, root_pt)


def build_body(body: RatBody, state: MotionState, floor_clearance: float = 1.5) -> BodyGeometry:
    """Ellipsoids and keypoints of ``body`` in every frame of ``state``.

    Args:
        body: the animal.
        state: its motion (T frames).
        floor_clearance: the torso and head are lifted so that they stay at least this far
            (mm) above the floor.

    Returns:
        :class:`BodyGeometry` with T frames: (T, N, 3) centres, (T, N, 3, 3) axes,
        (T, N, 3) radii and (T, 12, 3) keypoints.
    """
    D = _Dims(body)
    fr = _body_frames(D, state, floor_clearance)
    head = _torso_and_head(D, fr)
    front = _front_legs(D, fr, state)
    hind = _hind_legs(D, fr, state)
    tail = _tail(D, fr, state)
    T = len(state.yaw)
    n_parts = len(PART_NAMES)
    C = np.zeros((T, n_parts, 3))
    A = np.zeros((T, n_parts, 3, 3))
    Rd = np.zeros((T, n_parts, 3))
    for parts in (head.parts, front.parts, hind.parts, tail.parts):
        for name, (c, ax, r) in parts.items():
            i = PART[name]
            C[:, i], A[:, i], Rd[:, i] = c, ax, r
    ears, eyes, paws, ankles, tips = head.ears, head.eyes, front.paws, hind.ankles, hind.tips
    kp = np.stack(
        [ears[0], eyes[0], paws[:, 0], ankles[:, 0], tips[:, 0],
         ears[1], eyes[1], paws[:, 1], ankles[:, 1], tips[:, 1],
         head.nose_tip, tail.root],
        axis=1,
    )  # fmt: skip
    materials = PIEBALD_MATERIAL if body.appearance == "piebald" else PART_MATERIAL
    return BodyGeometry(C, A, Rd, kp, materials.copy())
