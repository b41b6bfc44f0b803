"""Behavioral variables per frame (method Table 5.2), fully vectorized over time.

For a skeleton with K keypoints, A angles and a ``window``-frame STFT with
F = window // 2 + 1 frequencies, the variables are, in this order:

========================  ==========  =====================================================
kind                      count       meaning (units)
========================  ==========  =====================================================
``local``                 K x 3       keypoint in the body frame, components x, y, z (mm)
``local_vel``             K x 3       time derivative of ``local`` (mm/s)
``origin_dist``           K           distance to the body-frame origin (mm)
``origin_dist_vel``       K           its time derivative (mm/s)
``origin_dist_stft``      K x F       STFT amplitude of ``origin_dist`` per frequency (mm)
``floor_dist``            K           signed distance to the floor plane (mm, + above)
``floor_dist_stft``       K x F       STFT amplitude of ``floor_dist`` per frequency (mm)
``angle``                 A           skeleton angles (degrees)
``angle_vel``             A           their time derivatives (degrees/s)
========================  ==========  =====================================================

For the 12-keypoint rat with 6 angles and 64-frame windows: 36+36+12+12+396+12+396+6+6 = 912.

A variable's *type* is its kind plus component (``local_x``, ``origin_dist_stft_9.38Hz``); its
*part* is the keypoint (or angle) it describes; its name is ``type[part]``, e.g.
``local_z[Paw Front Right]``, ``floor_dist_stft_9.38Hz[Nose]``, ``angle[head_pitch]``.

Conventions:

- **Up** is the floor's up-pointing normal (by default the poses file's ``up`` vector, i.e.
  the world z axis after ``freipose calib --origin-frame``).
- **Body frame** (skeleton ``[frame]``): origin at the mean of ``frame.origin`` (the rat's ear
  midpoint); z = up; y = the horizontal direction from the origin towards ``frame.toward``
  (the tail); x = y x z (the animal's left side), right-handed. Undefined (NaN) when the
  tail is straight above or below the origin.
- **Angles** (skeleton ``[angles]``, each a pair of vectors): when one vector is ``["g"]``
  (up), the angle is the *elevation* of the other vector above the horizontal plane,
  ``90° - ∠(up, v)`` in [-90°, 90°]: 0 for a level vector, positive when ``v`` points up. So a
  rat standing level has body elevation 0. Between two body vectors it is the unsigned
  angle ``∠(a, b)`` in [0°, 180°] (0 when they are parallel, e.g. head in line with body).
- **Velocities** are central differences times fps (one-sided at the ends).
- **STFT**: for every frame a ``window``-frame Hann window centred on the frame (frames
  ``t - window/2 .. t + window/2 - 1``; the signal is mirrored at the ends of the
  recording); the amplitude spectrum (|DFT| / sum(window), doubled except for the DC and
  Nyquist bins, so a sinusoid of amplitude A reads about A at its bin). Frequencies
  ``f_k = k · fps / window``, k = 0 .. window/2. A window that touches a missing value gives
  NaN for that frame.
- **Missing keypoints** (NaN) are linearly interpolated over gaps of at most ``max_gap_s``
  seconds (interior gaps only); longer gaps stay NaN, and so do the variables that use them.
  Frames missing from ``frame_index`` are inserted as NaN rows so the time axis is regular.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from freipose._frozen import PicklableFrozen
from freipose.analysis.floor import FloorPlane
from freipose.analysis.signals import (
    interpolate_gaps,
    stft_amplitude,
    stft_frequencies,
    time_derivative,
)
from freipose.errors import FreiPoseError
from freipose.skeleton import PointRef, Skeleton

log = logging.getLogger(__name__)

POINT_KINDS = ("local", "local_vel", "origin_dist", "origin_dist_vel", "floor_dist")
STFT_KINDS = ("origin_dist_stft", "floor_dist_stft")
ANGLE_KINDS = ("angle", "angle_vel")
KIND_UNITS: Mapping[str, str] = MappingProxyType(
    {
        "local": "mm",
        "local_vel": "mm/s",
        "origin_dist": "mm",
        "origin_dist_vel": "mm/s",
        "origin_dist_stft": "mm",
        "floor_dist": "mm",
        "floor_dist_stft": "mm",
        "angle": "deg",
        "angle_vel": "deg/s",
    }
)


class VariablesError(FreiPoseError):
    """Poses or a skeleton cannot give behavioral variables; the message says why."""


@dataclass(frozen=True)
class VariableConfig(PicklableFrozen):
    """Settings of :func:`compute_variables`.

    Attributes:
        max_gap_s: longest run of missing frames (seconds) filled by linear interpolation.
        stft_window: STFT window length in frames (even); gives ``stft_window // 2 + 1``
            frequencies (64 -> 33).
        chunk_frames: frames per STFT block (memory bound: about chunk x 2K x window x 4 B).
    """

    max_gap_s: float = 0.1
    stft_window: int = 64
    chunk_frames: int = 16384

    def __post_init__(self) -> None:
        if not (np.isfinite(self.max_gap_s) and self.max_gap_s >= 0):
            raise VariablesError(f"max_gap_s must be >= 0 seconds, got {self.max_gap_s}")
        if self.stft_window < 4 or self.stft_window % 2:
            raise VariablesError(f"stft_window must be an even number >= 4, got {self.stft_window}")
        if self.chunk_frames < 1:
            raise VariablesError(f"chunk_frames must be >= 1, got {self.chunk_frames}")


@dataclass(frozen=True, eq=False)
class Variables(PicklableFrozen):
    """Behavioral variables of one recording.

    Attributes:
        values: (T, V) float32, NaN where undefined.
        names: (V,) ``type[part]`` names.
        kinds: (V,) kind of each variable (see module docstring).
        components: (V,) ``x``/``y``/``z``, a frequency label such as ``9.38Hz``, or ``""``.
        parts: (V,) keypoint or angle name the variable describes.
        involved: (V, K) bool, the keypoints each variable is computed from (for local-frame
            variables the keypoint itself; the frame keypoints enter every one of them).
        keypoints: (K,) keypoint names.
        frame_index: (T,) int64 contiguous video frame numbers.
        fps: frames per second.
        frequencies: (F,) STFT frequencies in Hz.
        floor: the floor plane used (its normal is the up vector).
        info: facts about the computation (interpolated/missing counts, settings, source).
    """

    values: np.ndarray
    names: tuple[str, ...]
    kinds: tuple[str, ...]
    components: tuple[str, ...]
    parts: tuple[str, ...]
    involved: np.ndarray
    keypoints: tuple[str, ...]
    frame_index: np.ndarray
    fps: float
    frequencies: np.ndarray
    floor: FloorPlane
    info: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        t, v = self.values.shape
        for name in ("names", "kinds", "components", "parts"):
            if len(getattr(self, name)) != v:
                raise VariablesError(
                    f"{name} has {len(getattr(self, name))} entries for {v} variables"
                )
        if self.involved.shape != (v, len(self.keypoints)):
            raise VariablesError(f"involved must be (V, K) = {(v, len(self.keypoints))}")
        if self.frame_index.shape != (t,):
            raise VariablesError(f"frame_index must be ({t},), got {self.frame_index.shape}")
        if len(set(self.names)) != v:
            raise VariablesError("variable names are not unique")
        object.__setattr__(self, "info", MappingProxyType(dict(self.info)))

    @property
    def num_frames(self) -> int:
        """Number of frames T."""
        return self.values.shape[0]

    @property
    def types(self) -> tuple[str, ...]:
        """(V,) variable type: kind plus ``_component`` when there is one."""
        return tuple(k if not c else f"{k}_{c}" for k, c in zip(self.kinds, self.components))

    @property
    def times(self) -> np.ndarray:
        """(T,) seconds from the first frame."""
        return (self.frame_index - self.frame_index[0]) / self.fps

    def column(self, name: str) -> np.ndarray:
        """(T,) values of one variable by name."""
        try:
            return self.values[:, self.names.index(name)]
        except ValueError:
            raise KeyError(f"no variable {name!r}; names look like {self.names[:3]}") from None

    def involved_names(self, i: int) -> list[str]:
        """Keypoint names variable ``i`` is computed from."""
        return [self.keypoints[k] for k in np.flatnonzero(self.involved[i])]


# ----------------------------------------------------------------------------- helpers


def regular_time_axis(poses: np.ndarray, frame_index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Put poses on a contiguous frame grid, inserting NaN rows for skipped frames.

    Args:
        poses: (T, K, 3).
        frame_index: (T,) strictly increasing.

    Returns:
        poses (T', K, 3) and frame_index (T',) with T' = last - first + 1.
    """
    fi = np.asarray(frame_index, dtype=np.int64)
    if len(fi) and np.any(np.diff(fi) <= 0):
        bad = int(np.flatnonzero(np.diff(fi) <= 0)[0])
        raise VariablesError(
            f"frame_index must increase strictly; row {bad + 1} has frame {fi[bad + 1]} after "
            f"{fi[bad]}; sort the poses by frame and drop duplicates"
        )
    if len(fi) == 0 or fi[-1] - fi[0] + 1 == len(fi):
        return poses, fi
    grid = np.arange(fi[0], fi[-1] + 1, dtype=np.int64)
    out = np.full((len(grid),) + poses.shape[1:], np.nan, dtype=poses.dtype)
    out[fi - fi[0]] = poses
    log.info("%d frames missing from frame_index were inserted as NaN", len(grid) - len(fi))
    return out, grid


def _freq_labels(freqs: np.ndarray) -> list[str]:
    labels = [f"{f:.3g}Hz" for f in freqs]
    if len(set(labels)) != len(labels):
        labels = [f"f{k:02d}" for k in range(len(freqs))]
    return labels


def _point(poses: np.ndarray, ref: PointRef) -> np.ndarray:
    return poses[:, list(ref), :].mean(axis=1)


def body_frame(
    poses: np.ndarray, skeleton: Skeleton, up: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Origin and axes of the body frame per frame.

    Args:
        poses: (T, K, 3) world mm.
        skeleton: defines the body frame (``[frame]`` origin and toward).
        up: (3,) unit up vector.

    Returns:
        origin (T, 3) and rotation (T, 3, 3) whose rows are the body x, y, z axes in world
        coordinates, so ``local = rotation @ (X - origin)``. NaN where undefined.
    """
    frame = skeleton.frame
    if "origin" not in frame or "toward" not in frame:
        raise VariablesError(
            f"skeleton {skeleton.name!r} defines no body frame; add a [frame] table with "
            f"origin = [...] and toward = [...] keypoint names to its TOML file"
        )
    up = np.asarray(up, dtype=np.float64)
    origin = _point(poses, frame["origin"])
    toward = _point(poses, frame["toward"]) - origin
    horiz = toward - (toward @ up)[:, None] * up
    norm = np.linalg.norm(horiz, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        y = np.where(norm > 1e-9, horiz / norm, np.nan)
    z = np.broadcast_to(up, y.shape)
    x = np.cross(y, z)
    return origin, np.stack([x, y, z], axis=1)


def _vector(poses: np.ndarray, vec: Any, up: np.ndarray) -> np.ndarray | None:
    if tuple(vec) == ("g",):
        return None
    a, b = vec
    return _point(poses, b) - _point(poses, a)


def skeleton_angles(poses: np.ndarray, skeleton: Skeleton, up: np.ndarray) -> np.ndarray:
    """The skeleton's angles in degrees (conventions in the module docstring).

    Args:
        poses: (T, K, 3).
        skeleton: defines the angles.
        up: (3,) unit up vector.

    Returns:
        (T, A) degrees in the order of ``skeleton.angles``.
    """
    up = np.asarray(up, dtype=np.float64)
    out = np.empty((poses.shape[0], len(skeleton.angles)))
    for j, (name, (va, vb)) in enumerate(skeleton.angles.items()):
        a, b = _vector(poses, va, up), _vector(poses, vb, up)
        if a is None and b is None:
            raise VariablesError(f"skeleton angle {name!r}: both vectors are 'g'")
        if a is None or b is None:
            v = b if a is None else a
            vert = v @ up
            hor = np.linalg.norm(v - vert[:, None] * up, axis=1)
            val = np.degrees(np.arctan2(vert, hor))
            degenerate = np.linalg.norm(v, axis=1) < 1e-9
        else:
            cr = np.linalg.norm(np.cross(a, b), axis=1)
            val = np.degrees(np.arctan2(cr, np.einsum("ti,ti->t", a, b)))
            degenerate = (np.linalg.norm(a, axis=1) < 1e-9) | (np.linalg.norm(b, axis=1) < 1e-9)
        # A zero-length vector has no direction: the angle is undefined.
        out[:, j] = np.where(degenerate, np.nan, val)
    return out


def _involved_refs(skeleton: Skeleton, vecs: tuple[Any, Any]) -> set[int]:
    ids: set[int] = set()
    for v in vecs:
        if tuple(v) != ("g",):
            for ref in v:
                ids.update(ref)
    return ids


@dataclass(frozen=True)
class VariableLayout(PicklableFrozen):
    """Names and metadata of the variables a skeleton gives (order of ``Variables.values``)."""

    names: tuple[str, ...]
    kinds: tuple[str, ...]
    components: tuple[str, ...]
    parts: tuple[str, ...]
    involved: np.ndarray
    offsets: Mapping[str, int]


def variable_layout(skeleton: Skeleton, frequencies: np.ndarray) -> VariableLayout:
    """The variable table for ``skeleton`` and STFT ``frequencies`` (see module docstring)."""
    kps = skeleton.keypoints
    k = len(kps)
    flabels = _freq_labels(np.asarray(frequencies))
    kinds: list[str] = []
    comps: list[str] = []
    parts: list[str] = []
    inv: list[set[int]] = []
    offsets: dict[str, int] = {}

    def add(kind: str, components: list[str]) -> None:
        offsets[kind] = len(kinds)
        for i in range(k):
            for c in components:
                kinds.append(kind)
                comps.append(c)
                parts.append(kps[i])
                inv.append({i})

    add("local", ["x", "y", "z"])
    add("local_vel", ["x", "y", "z"])
    add("origin_dist", [""])
    add("origin_dist_vel", [""])
    add("origin_dist_stft", flabels)
    add("floor_dist", [""])
    add("floor_dist_stft", flabels)
    for kind in ANGLE_KINDS:
        offsets[kind] = len(kinds)
        for name, vecs in skeleton.angles.items():
            kinds.append(kind)
            comps.append("")
            parts.append(name)
            inv.append(_involved_refs(skeleton, vecs))
    names = tuple(f"{kd}_{c}[{p}]" if c else f"{kd}[{p}]" for kd, c, p in zip(kinds, comps, parts))
    involved = np.zeros((len(names), k), dtype=bool)
    for i, ids in enumerate(inv):
        involved[i, sorted(ids)] = True
    return VariableLayout(names, tuple(kinds), tuple(comps), tuple(parts), involved, offsets)


def check_keypoints(keypoints: tuple[str, ...], skeleton: Skeleton, source: str = "poses") -> None:
    """Raise a clear error when the poses' keypoints are not the skeleton's (same order)."""
    if tuple(keypoints) != tuple(skeleton.keypoints):
        missing = [k for k in skeleton.keypoints if k not in keypoints]
        extra = [k for k in keypoints if k not in skeleton.keypoints]
        what = (
            f"missing {missing}, unexpected {extra}"
            if (missing or extra)
            else "same names in a different order"
        )
        raise VariablesError(
            f"{source}: keypoints {list(keypoints)} do not match skeleton {skeleton.name!r} "
            f"{list(skeleton.keypoints)} ({what}); pass the skeleton the poses were made with "
            f"(--skeleton NAME|FILE)"
        )


@dataclass(frozen=True)
class PreparedPoses:
    """Poses on a regular time axis with short gaps filled (input of the variables).

    Attributes:
        poses: (T, K, 3) float64 world mm, NaN = missing keypoint.
        frame_index: (T,) int64 contiguous video frames.
        fps: frames per second.
        missing: keypoint positions missing before the interpolation.
        interpolated: keypoint positions filled by the interpolation.
        max_gap: longest filled gap in frames.
    """

    poses: np.ndarray
    frame_index: np.ndarray
    fps: float
    missing: int
    interpolated: int
    max_gap: int


def prepare_poses(
    poses: np.ndarray,
    frame_index: np.ndarray,
    fps: float,
    skeleton: Skeleton,
    config: VariableConfig,
    keypoints: tuple[str, ...] | None = None,
) -> PreparedPoses:
    """Check the poses, put them on a regular time axis and fill short gaps.

    Args:
        poses: (T, K, 3) world mm, NaN = missing; K = the skeleton's keypoints.
        frame_index: (T,) strictly increasing video frames (gaps are filled with NaN rows).
        fps: frames per second.
        skeleton: defines the keypoint order.
        config: the longest filled gap and the STFT window (the shortest recording).
        keypoints: the poses' keypoint names, checked against the skeleton when given.

    Returns:
        The prepared poses (T' = frame_index[-1] - frame_index[0] + 1 frames).

    Raises:
        VariablesError: keypoints, shape or fps do not fit, or the recording is too short.
    """
    if keypoints is not None:
        check_keypoints(tuple(keypoints), skeleton)
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (skeleton.num_keypoints, 3):
        raise VariablesError(
            f"poses must be (T, {skeleton.num_keypoints}, 3) for skeleton {skeleton.name!r}, "
            f"got {poses.shape}"
        )
    fps = float(fps)
    if not (np.isfinite(fps) and fps > 0):
        raise VariablesError(f"fps must be positive, got {fps}")
    poses, fidx = regular_time_axis(poses, frame_index)
    t = poses.shape[0]
    if t <= config.stft_window // 2:
        raise VariablesError(
            f"recording too short: {t} frames; the {config.stft_window}-frame STFT needs more "
            f"than {config.stft_window // 2}"
        )
    # A keypoint with any NaN coordinate is missing as a whole.
    poses[np.isnan(poses).any(axis=2)] = np.nan
    missing_before = int(np.isnan(poses[..., 0]).sum())
    max_gap = int(np.floor(config.max_gap_s * fps + 1e-9))
    poses, n_filled = interpolate_gaps(poses, max_gap)
    return PreparedPoses(poses, fidx, fps, missing_before, n_filled // 3, max_gap)


def fill_point_variables(
    out: np.ndarray,
    layout: VariableLayout,
    prep: PreparedPoses,
    skeleton: Skeleton,
    floor: FloorPlane,
    config: VariableConfig,
) -> None:
    """Write the keypoint variables (body frame, distances, velocities, STFTs) into ``out``.

    Args:
        out: (T, V) float32 values, filled in place at the kinds' offsets in ``layout``.
        layout: the variables' layout.
        prep: the prepared poses.
        skeleton: defines the body frame.
        floor: floor plane; its normal is the up vector.
        config: STFT window and block size.
    """
    poses, fps = prep.poses, prep.fps
    t, k, _ = poses.shape
    off = layout.offsets
    origin, rot = body_frame(poses, skeleton, floor.normal)
    local = np.einsum("tij,tkj->tki", rot, poses - origin[:, None, :])  # (T, K, 3)
    out[:, off["local"] : off["local"] + 3 * k] = local.reshape(t, 3 * k)
    vel = time_derivative(local, fps)
    out[:, off["local_vel"] : off["local_vel"] + 3 * k] = vel.reshape(t, 3 * k)
    odist = np.linalg.norm(local, axis=2)  # (T, K)
    out[:, off["origin_dist"] : off["origin_dist"] + k] = odist
    out[:, off["origin_dist_vel"] : off["origin_dist_vel"] + k] = time_derivative(odist, fps)
    fdist = floor.distance(poses)  # (T, K)
    out[:, off["floor_dist"] : off["floor_dist"] + k] = fdist
    spec = stft_amplitude(
        np.concatenate([odist, fdist], axis=1), config.stft_window, config.chunk_frames
    )  # (T, 2K, F)
    nf = spec.shape[2]
    out[:, off["origin_dist_stft"] : off["origin_dist_stft"] + k * nf] = spec[:, :k].reshape(t, -1)
    out[:, off["floor_dist_stft"] : off["floor_dist_stft"] + k * nf] = spec[:, k:].reshape(t, -1)


def fill_angle_variables(
    out: np.ndarray, layout: VariableLayout, prep: PreparedPoses, skeleton: Skeleton, up: np.ndarray
) -> None:
    """Write the skeleton's angles and their velocities into ``out``.

    Args:
        out: (T, V) float32 values, filled in place at the kinds' offsets in ``layout``.
        layout: the variables' layout.
        prep: the prepared poses.
        skeleton: defines the angles.
        up: (3,) unit up vector.
    """
    na = len(skeleton.angles)
    if not na:
        return
    off = layout.offsets
    ang = skeleton_angles(prep.poses, skeleton, up)
    out[:, off["angle"] : off["angle"] + na] = ang
    out[:, off["angle_vel"] : off["angle_vel"] + na] = time_derivative(ang, prep.fps)


def compute_variables(
    poses: np.ndarray,
    frame_index: np.ndarray,
    fps: float,
    skeleton: Skeleton,
    floor: FloorPlane,
    config: VariableConfig = VariableConfig(),
    keypoints: tuple[str, ...] | None = None,
) -> Variables:
    """All behavioral variables of one recording (see the module docstring).

    Args:
        poses: (T, K, 3) world mm, NaN = missing; K = the skeleton's keypoints.
        frame_index: (T,) strictly increasing video frames (gaps are filled with NaN rows).
        fps: frames per second.
        skeleton: defines the body frame, the angles and the keypoint order.
        floor: floor plane; its normal is the up vector.
        config: gap filling and STFT settings.
        keypoints: the poses' keypoint names, checked against the skeleton when given.

    Returns:
        Variables with values (T', V) float32, T' = frame_index[-1] - frame_index[0] + 1.

    Raises:
        VariablesError: the poses do not fit the skeleton or are too short.
    """
    prep = prepare_poses(poses, frame_index, fps, skeleton, config, keypoints)
    t = prep.poses.shape[0]
    freqs = stft_frequencies(config.stft_window, prep.fps)
    layout = variable_layout(skeleton, freqs)
    out = np.empty((t, len(layout.names)), dtype=np.float32)
    fill_point_variables(out, layout, prep, skeleton, floor, config)
    fill_angle_variables(out, layout, prep, skeleton, floor.normal)
    nan_frames = int(np.isnan(out).any(axis=1).sum())
    info = {
        "keypoints_missing": prep.missing,
        "keypoints_interpolated": prep.interpolated,
        "frames_with_nan": nan_frames,
        "max_gap_s": config.max_gap_s,
        "max_gap_frames": prep.max_gap,
        "stft_window": config.stft_window,
        "skeleton": skeleton.name,
    }
    if nan_frames:
        log.info(
            "%d of %d frames have undefined variables (missing keypoints beyond %d-frame gaps, "
            "and the STFT windows around them)",
            nan_frames,
            t,
            prep.max_gap,
        )
    return Variables(
        values=out,
        names=layout.names,
        kinds=layout.kinds,
        components=layout.components,
        parts=layout.parts,
        involved=layout.involved,
        keypoints=tuple(skeleton.keypoints),
        frame_index=prep.frame_index,
        fps=prep.fps,
        frequencies=freqs,
        floor=floor,
        info=info,
    )
