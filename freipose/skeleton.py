"""Skeleton definitions: keypoint names and order, limbs, left/right symmetry, analysis frames.

Shipped skeletons (``rat``, ``mouse``, ``paw``) live in ``freipose/skeletons/*.toml``;
users pass their own TOML file with the same fields (see ``docs/formats.md``).
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

from freipose._frozen import PicklableFrozen
from freipose.errors import FreiPoseError, InputFileError
from freipose.io.toml import parse_toml

# A limb end or an analysis point: one keypoint index, or a tuple of indices (their mean).
PointRef = tuple[int, ...]

BUILTIN_SKELETONS = ("rat", "mouse", "paw")

# Spellings of left and right inside keypoint names (a name's side is the first one found).
_LR = (("left", "right"), ("Left", "Right"), ("LEFT", "RIGHT"), ("_l", "_r"), ("_L", "_R"))


class SkeletonError(FreiPoseError):
    """A skeleton definition is malformed; the message names the file and the field."""


class UnknownKeypointError(SkeletonError, KeyError):
    """A keypoint name that the skeleton does not have."""


@dataclass(frozen=True, eq=False)
class Skeleton(PicklableFrozen):
    """Keypoints of an animal model and how they connect.

    Attributes:
        name: skeleton name.
        keypoints: keypoint names in order (the keypoint axis of every array).
        limbs: pairs of ends; each end is a tuple of keypoint indices whose mean is the end.
        symmetry: (left, right) index pairs of mirror-image keypoints.
        feet: indices of keypoints that touch the floor when standing.
        frame: analysis body frame, ``{"origin": PointRef, "toward": PointRef}`` (may be empty).
        angles: analysis angles, name -> (vector_a, vector_b); a vector is ``("g",)`` for the
            world up vector or ``(from PointRef, to PointRef)``.
    """

    name: str
    keypoints: tuple[str, ...]
    limbs: tuple[tuple[PointRef, PointRef], ...] = ()
    symmetry: tuple[tuple[int, int], ...] = ()
    feet: tuple[int, ...] = ()
    frame: Mapping[str, PointRef] = field(default_factory=dict)
    angles: Mapping[str, tuple[Any, Any]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        kps = tuple(self.keypoints)
        if not kps:
            raise SkeletonError(f"skeleton {self.name!r} has no keypoints")
        dupes = sorted({k for k in kps if kps.count(k) > 1})
        if dupes:
            raise SkeletonError(f"skeleton {self.name!r}: repeated keypoint names {dupes}")
        object.__setattr__(self, "keypoints", kps)
        object.__setattr__(self, "frame", MappingProxyType(dict(self.frame)))
        object.__setattr__(self, "angles", MappingProxyType(dict(self.angles)))
        n = len(kps)
        for limb in self.limbs:
            for end in limb:
                if not end or any(not 0 <= i < n for i in end):
                    raise SkeletonError(f"skeleton {self.name!r}: limb end {end} out of range")

    @property
    def num_keypoints(self) -> int:
        """The number of keypoints K."""
        return len(self.keypoints)

    def index(self, name: str) -> int:
        """The index of keypoint ``name``.

        Raises:
            UnknownKeypointError: the skeleton has no such keypoint (a ``KeyError`` too).
        """
        try:
            return self.keypoints.index(name)
        except ValueError:
            raise UnknownKeypointError(
                f"skeleton {self.name!r} has no keypoint {name!r}; it has {list(self.keypoints)}"
            ) from None

    def point(self, poses: np.ndarray, ref: PointRef) -> np.ndarray:
        """The (mean) position of a point reference: poses (..., K, D) -> (..., D)."""
        return np.mean(poses[..., list(ref), :], axis=-2)

    def limb_lengths(self, poses: np.ndarray) -> np.ndarray:
        """Limb lengths of 3D poses (..., K, 3) -> (..., L)."""
        return np.stack(
            [
                np.linalg.norm(self.point(poses, b) - self.point(poses, a), axis=-1)
                for a, b in self.limbs
            ],
            axis=-1,
        )

    def mirror_permutation(self) -> np.ndarray:
        """Index permutation (K,) that swaps left and right keypoints."""
        perm = np.arange(self.num_keypoints)
        for a, b in self.symmetry:
            perm[a], perm[b] = b, a
        return perm

    def to_dict(self) -> dict[str, Any]:
        """A TOML-ready dict using keypoint names (inverse of :func:`skeleton_from_dict`)."""

        def ref(r: PointRef) -> Any:
            return self.keypoints[r[0]] if len(r) == 1 else [self.keypoints[i] for i in r]

        def vec(v: Any) -> list[Any]:
            return ["g"] if tuple(v) == ("g",) else [ref(v[0]), ref(v[1])]

        d: dict[str, Any] = {
            "name": self.name,
            "keypoints": list(self.keypoints),
            "limbs": [[ref(a), ref(b)] for a, b in self.limbs],
            "symmetry": [[self.keypoints[a], self.keypoints[b]] for a, b in self.symmetry],
            "feet": [self.keypoints[i] for i in self.feet],
        }
        if self.frame:
            d["frame"] = {k: [self.keypoints[i] for i in v] for k, v in self.frame.items()}
        if self.angles:
            d["angles"] = {k: [vec(a), vec(b)] for k, (a, b) in self.angles.items()}
        return d


def infer_symmetry(keypoints: Sequence[str]) -> list[tuple[int, int]]:
    """Left/right pairs from the keypoint names.

    Names such as ``Ear Left``/``Ear Right``, ``leftear``/``rightear``,
    ``Haunch_left``/``Haunch_right`` and ``EarL``/``EarR`` pair up.

    Args:
        keypoints: (K,) keypoint names.

    Returns:
        (left, right) index pairs.
    """
    names = list(keypoints)
    pairs = []
    for i, a in enumerate(names):
        cands = []
        for left, right in _LR:
            if left in a:
                cands.append(a.replace(left, right))
        m = re.fullmatch(r"(.+)L", a)
        if m:
            cands.append(m.group(1) + "R")
        for b in cands:
            if b in names and b != a:
                pairs.append((i, names.index(b)))
                break
    return pairs


def _is_right(name: str) -> bool:
    """Whether a keypoint name says right (``Right``, ``right``, ``_r``, a final ``R``)."""
    return any(r in name for _, r in _LR) or bool(re.fullmatch(r".+[a-z]R", name))


def left_right_pairs(skeleton: Skeleton) -> tuple[tuple[int, int], ...]:
    """The (left, right) keypoint index pairs of a skeleton.

    The skeleton's declared ``symmetry`` pairs, each ordered left first where the names
    say which side is which; without declared pairs, the pairs that :func:`infer_symmetry`
    finds in the keypoint names.

    Args:
        skeleton: the skeleton.

    Returns:
        (left, right) index pairs (empty for a skeleton without mirror-image keypoints).
    """
    if not skeleton.symmetry:
        return tuple(infer_symmetry(skeleton.keypoints))
    kps = skeleton.keypoints
    return tuple(
        (b, a) if _is_right(kps[a]) and not _is_right(kps[b]) else (a, b)
        for a, b in skeleton.symmetry
    )


def _ref(names: Sequence[str], value: Any, where: str, skel: str) -> PointRef:
    items = [value] if isinstance(value, str) else list(value)
    out = []
    for v in items:
        if not isinstance(v, str) or v not in names:
            raise SkeletonError(
                f"skeleton {skel!r}: {where} names unknown keypoint {v!r}; known: {list(names)}"
            )
        out.append(names.index(v))
    return tuple(out)


def skeleton_from_dict(data: Mapping[str, Any], source: str = "<dict>") -> Skeleton:
    """Build a ``Skeleton`` from the TOML structure documented in ``docs/formats.md``."""
    for key in ("name", "keypoints"):
        if key not in data:
            raise SkeletonError(f"skeleton file {source}: missing required field {key!r}")
    name = str(data["name"])
    if isinstance(data["keypoints"], str) or not isinstance(data["keypoints"], Sequence):
        raise SkeletonError(
            f"skeleton file {source}: keypoints must be a list of names, got {data['keypoints']!r}"
        )
    kps = [str(k) for k in data["keypoints"]]
    limbs = []
    for i, limb in enumerate(data.get("limbs", [])):
        if len(limb) != 2:
            raise SkeletonError(
                f"skeleton file {source}: limb {i} must have two ends, got {limb!r}"
            )
        limbs.append((_ref(kps, limb[0], f"limb {i}", name), _ref(kps, limb[1], f"limb {i}", name)))
    sym = []
    for pair in data.get("symmetry", []):
        if isinstance(pair, str) or len(pair) != 2:
            raise SkeletonError(
                f"skeleton file {source}: a symmetry entry must be two names, got {pair!r}"
            )
        a, b = (_ref(kps, p, "symmetry", name) for p in pair)
        sym.append((a[0], b[0]))
    feet = tuple(_ref(kps, f, "feet", name)[0] for f in data.get("feet", []))
    frame = {k: _ref(kps, v, f"frame.{k}", name) for k, v in dict(data.get("frame", {})).items()}
    angles = {}
    for aname, pair in dict(data.get("angles", {})).items():
        if isinstance(pair, str) or len(pair) != 2:
            raise SkeletonError(
                f"skeleton file {source}: angle {aname!r} must be two vectors [A, B], got {pair!r}"
            )
        va, vb = pair

        def vec(v: Any, aname: str = aname) -> Any:
            if list(v) == ["g"]:
                return ("g",)
            if len(v) != 2:
                raise SkeletonError(
                    f"skeleton file {source}: angle {aname!r} vector must be ['g'] or [FROM, TO]"
                )
            return (
                _ref(kps, v[0], f"angle {aname}", name),
                _ref(kps, v[1], f"angle {aname}", name),
            )

        angles[aname] = (vec(va), vec(vb))
    return Skeleton(name, tuple(kps), tuple(limbs), tuple(sym), feet, frame, angles)


def load_skeleton(name_or_path: str | Path) -> Skeleton:
    """Load a shipped skeleton by name (``rat``, ``mouse``, ``paw``) or a TOML file by path."""
    text: str
    source = str(name_or_path)
    if str(name_or_path) in BUILTIN_SKELETONS:
        text = resources.files("freipose.skeletons").joinpath(f"{name_or_path}.toml").read_text()
    else:
        path = Path(name_or_path)
        if not path.is_file():
            raise InputFileError(
                f"skeleton {source!r} is neither a shipped skeleton {list(BUILTIN_SKELETONS)} "
                f"nor an existing TOML file"
            )
        text = path.read_text()
    return skeleton_from_dict(parse_toml(text, source, "skeleton file", SkeletonError), source)
