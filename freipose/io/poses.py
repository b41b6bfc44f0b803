"""Predictions file ``poses.h5``: 3D poses with confidences (schema in ``docs/formats.md``).

Required: ``poses`` float32 (T, K, 3) world mm (NaN = missing), ``confidence`` float32
(T, K) in [0, 1], ``keypoints`` (K,) UTF-8, ``frame_index`` (T,) int64; root attributes
``fps``, ``units = "mm"``, ``up`` (3,), ``freipose_version``. Optional: the calibration
(``calibration`` attribute, calibration.toml text), the skeleton (``skeleton`` attribute,
skeleton TOML text), provenance attributes (``provenance/...``) and extra per-frame
datasets under ``extra/`` (e.g. ``points2d`` (T, C, K, 2), ``boxes`` (T, C, 4),
``center`` (T, 3)).

Several animals: a file with the dataset ``individuals`` (A,) UTF-8 has an animal axis
after time: ``poses`` (T, A, K, 3), ``confidence`` (T, A, K), the per-animal extras
(``points2d`` (T, A, C, K, 2), ``center`` (T, A, 3), ...) and optionally
``identity_confidence`` (T, A) float32 in [0, 1] (how sure the identity of each animal's
row is in each frame). A file without ``individuals`` holds one animal.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

import h5py
import numpy as np
import tomli_w

from freipose import __version__
from freipose._frozen import PicklableFrozen
from freipose.errors import FreiPoseError
from freipose.geometry.camera import CameraRig
from freipose.io.atomic import atomic_h5
from freipose.io.calibration_toml import rig_from_toml_text, rig_to_toml_text
from freipose.io.hdf5 import decode_strings, open_h5, str_array
from freipose.io.movement import SUFFIX as MOVEMENT_SUFFIX
from freipose.io.movement import MovementPoses, read_movement, write_movement
from freipose.io.toml import parse_toml
from freipose.skeleton import Skeleton, skeleton_from_dict

SCHEMA = "freipose.poses"
SCHEMA_VERSION = 1


class PosesFormatError(FreiPoseError):
    """A poses file is malformed; the message names the file and the problem."""


@dataclass(frozen=True, eq=False)
class PoseData(PicklableFrozen):
    """3D poses of one recording.

    Attributes:
        poses: (T, K, 3) float32 world mm, NaN where missing.
        confidence: (T, K) float32 in [0, 1] (0 where missing).
        keypoints: (K,) keypoint names.
        frame_index: (T,) int64 video frame numbers.
        fps: frames per second of the source videos.
        up: (3,) world up vector (unit).
        calibration: the cameras, if known.
        skeleton: the skeleton, if known.
        provenance: free-form facts (versions, model hash, source videos).
        extra: further per-frame arrays with time as the first axis.
        individuals: (A,) animal names: the poses have an animal axis (T, A, K, 3); None:
            one animal without an axis (T, K, 3).
        identity_confidence: (T, A) float32 in [0, 1]: how sure each row's identity is
            (only with ``individuals``; None: not known).

    With ``individuals`` the confidences are (T, A, K) and the per-animal extras
    (:data:`ANIMAL_EXTRAS`) have the animal axis after time; :meth:`animal` gives one
    animal as a single-animal :class:`PoseData`, ``freipose.io.animals.stack_animals`` joins them.
    """

    poses: np.ndarray
    confidence: np.ndarray
    keypoints: tuple[str, ...]
    frame_index: np.ndarray
    fps: float
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    calibration: CameraRig | None = None
    skeleton: Skeleton | None = None
    provenance: Mapping[str, Any] = field(default_factory=dict)
    extra: Mapping[str, np.ndarray] = field(default_factory=dict)
    individuals: tuple[str, ...] | None = None
    identity_confidence: np.ndarray | None = None

    def __post_init__(self) -> None:
        poses = np.asarray(self.poses, dtype=np.float32)
        animals = self._checked_individuals(poses)
        if animals is None and (poses.ndim != 3 or poses.shape[-1] != 3):
            raise PosesFormatError(f"poses must have shape (T, K, 3), got {poses.shape}")
        t, k = poses.shape[0], poses.shape[-2]
        lead = (t,) if animals is None else (t, len(animals))
        conf = np.asarray(self.confidence, dtype=np.float32)
        if conf.shape != (*lead, k):
            raise PosesFormatError(f"confidence must have shape {(*lead, k)}, got {conf.shape}")
        if np.any(conf[np.isfinite(conf)] < 0) or np.any(conf[np.isfinite(conf)] > 1):
            raise PosesFormatError("confidence values must lie in [0, 1]")
        kps = tuple(str(s) for s in self.keypoints)
        if len(kps) != k:
            raise PosesFormatError(f"{len(kps)} keypoint names for {k} keypoints in poses")
        fi = np.asarray(self.frame_index, dtype=np.int64)
        if fi.shape != (t,):
            raise PosesFormatError(f"frame_index must have shape ({t},), got {fi.shape}")
        fps = float(self.fps)
        if not np.isfinite(fps) or fps <= 0:
            raise PosesFormatError(f"fps must be a positive number, got {self.fps!r}")
        up = np.asarray(self.up, dtype=np.float64).reshape(-1)
        if up.shape != (3,) or not np.isfinite(up).all() or np.linalg.norm(up) == 0:
            raise PosesFormatError(f"up must be a non-zero 3-vector, got {self.up!r}")
        if self.skeleton is not None and tuple(self.skeleton.keypoints) != kps:
            raise PosesFormatError(
                f"skeleton {self.skeleton.name!r} keypoints {list(self.skeleton.keypoints)} do not "
                f"match the poses' keypoints {list(kps)}"
            )
        cams = None if self.calibration is None else len(self.calibration)
        extra = _checked_extra(self.extra, t, k, cams, None if animals is None else len(animals))
        ident = self.identity_confidence
        if ident is not None:
            if animals is None:
                raise PosesFormatError("identity_confidence needs individuals (an animal axis)")
            ident = np.asarray(ident, dtype=np.float32)
            if ident.shape != lead:
                raise PosesFormatError(
                    f"identity_confidence must have shape {lead} (T, A), got {ident.shape}"
                )
            fin = ident[np.isfinite(ident)]
            if np.any(fin < 0) or np.any(fin > 1):
                raise PosesFormatError("identity_confidence values must lie in [0, 1]")
        object.__setattr__(self, "individuals", animals)
        object.__setattr__(self, "identity_confidence", ident)
        object.__setattr__(self, "poses", poses)
        object.__setattr__(self, "confidence", conf)
        object.__setattr__(self, "keypoints", kps)
        object.__setattr__(self, "frame_index", fi)
        object.__setattr__(self, "fps", fps)
        object.__setattr__(self, "up", up / np.linalg.norm(up))
        object.__setattr__(self, "provenance", MappingProxyType(dict(self.provenance)))
        object.__setattr__(self, "extra", MappingProxyType(extra))

    def _checked_individuals(self, poses: np.ndarray) -> tuple[str, ...] | None:
        """The animal names, checked against ``poses`` (None: no animal axis)."""
        if self.individuals is None:
            return None
        names = tuple(str(n) for n in self.individuals)
        if poses.ndim != 4 or poses.shape[-1] != 3 or poses.shape[1] != len(names):
            raise PosesFormatError(
                f"poses of {len(names)} individuals must have shape (T, {len(names)}, K, 3), "
                f"got {poses.shape}"
            )
        if len(set(names)) != len(names) or not all(names):
            raise PosesFormatError(f"individuals must be unique, non-empty names, got {names}")
        return names

    @property
    def num_frames(self) -> int:
        """The number of frames T."""
        return self.poses.shape[0]

    @property
    def num_animals(self) -> int:
        """The number of animals A (1 without an animal axis)."""
        return 1 if self.individuals is None else len(self.individuals)

    @property
    def animal_names(self) -> tuple[str, ...]:
        """(A,) the animals' names (``("animal",)`` without an animal axis)."""
        return ("animal",) if self.individuals is None else self.individuals

    def animal_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """``(poses (T, A, K, 3), confidence (T, A, K))``, with A = 1 for one animal."""
        if self.individuals is None:
            return self.poses[:, None], self.confidence[:, None]
        return self.poses, self.confidence

    def animal(self, which: int | str) -> PoseData:
        """One animal as a single-animal :class:`PoseData` (no animal axis).

        Args:
            which: the animal's index or name.

        Returns:
            Its poses, confidences and per-animal extras; the per-frame extras, the
            calibration, skeleton and provenance (plus ``individual``: its name) as they are.

        Raises:
            PosesFormatError: no such animal.
        """
        names = self.animal_names
        if isinstance(which, str):
            if which not in names:
                raise PosesFormatError(f"no animal {which!r}; the poses hold {list(names)}")
            i = names.index(which)
        else:
            i = int(which)
            if not 0 <= i < len(names):
                raise PosesFormatError(f"no animal {i}; the poses hold {len(names)}")
        if self.individuals is None:
            return self
        extra = {
            k: (v[:, i] if k in ANIMAL_EXTRAS else v) for k, v in self.extra.items()
        }  # fmt: skip
        return PoseData(
            self.poses[:, i], self.confidence[:, i], self.keypoints, self.frame_index,
            self.fps, self.up, self.calibration, self.skeleton,
            {**dict(self.provenance), "individual": names[i]}, extra,
        )  # fmt: skip

    @property
    def times(self) -> np.ndarray:
        """(T,) seconds from the first frame of the video (frame_index / fps)."""
        return self.frame_index / self.fps


#: the documented extra datasets that hold one value per animal: with an animal axis their
#: shape has A after T (``points2d`` (T, A, C, K, 2)); the others are per frame
ANIMAL_EXTRAS = frozenset(
    ("points2d", "confidence2d", "boxes", "center", "smooth_std", "filled", "rejected",
     "smooth_weight", "smooth_offset", "uncertainty", "identity_flagged", "identity_order",
     # the truth of synthetic scenes of several animals (freipose.synth.social_scene)
     "visible2d", "hidden_by_animal", "on_top_of", "lift", "contact")
)  # fmt: skip

# The documented extra datasets: their shapes in T (frames), C (cameras) and K (keypoints).
_EXTRA_SHAPES: Mapping[str, tuple[int | str, ...]] = MappingProxyType(
    {
        "points2d": ("T", "C", "K", 2),
        "confidence2d": ("T", "C", "K"),
        "boxes": ("T", "C", 4),
        "center": ("T", 3),
        "status": ("T",),
        "frame_ok": ("T", "C"),
        "smooth_std": ("T", "K", 3),
        "filled": ("T", "K"),
        "rejected": ("T", "K"),
        "uncertainty": ("T", "K"),
        "identity_flagged": ("T",),
        "identity_order": ("T",),
    }
)


def _checked_extra(
    extra: Mapping[str, Any], t: int, k: int, cams: int | None, animals: int | None = None
) -> dict[str, np.ndarray]:
    """The extra datasets as arrays, their shapes checked against T, K and the cameras C.

    Every extra dataset has T rows; the documented ones (:data:`_EXTRA_SHAPES`) have their
    full shape checked, with C the calibration's cameras, else the first dataset's; with
    ``animals`` A, those of :data:`ANIMAL_EXTRAS` have the animal axis after T.

    Raises:
        PosesFormatError: a dataset whose shape disagrees; the message names it, its
            shape, the expected one and the array it disagrees with.
    """
    sizes: dict[str, int] = {"T": t, "K": k}
    source = {"T": "the poses' frames", "K": "the poses' keypoints"}
    if animals is not None:
        sizes["A"], source["A"] = animals, "the individuals"
    if cams is not None:
        sizes["C"], source["C"] = cams, "the calibration's cameras"
    out = {}
    for name, arr in dict(extra).items():
        a = np.asarray(arr)
        spec = _EXTRA_SHAPES.get(name, ("T",))
        if animals is not None and name in ANIMAL_EXTRAS:
            spec = ("T", "A", *spec[1:])
        if "C" in spec and "C" not in sizes and a.ndim == len(spec):
            sizes["C"], source["C"] = a.shape[spec.index("C")], f"extra dataset {name!r}"
        expected = tuple(sizes.get(d, -1) if isinstance(d, str) else d for d in spec)
        got = a.shape[: len(spec)] if name not in _EXTRA_SHAPES else a.shape
        if got != expected:
            dims = ", ".join(map(str, spec)) + (", ..." if name not in _EXTRA_SHAPES else "")
            bad = [d for d, n, e in zip(spec, got, expected) if isinstance(d, str) and n != e]
            why = f"; {bad[0]}={sizes[bad[0]]} from {source[bad[0]]}" if bad else ""
            raise PosesFormatError(
                f"extra dataset {name!r} has shape {a.shape}, expected ({dims}) = {expected}{why}"
            )
        out[name] = a
    return out


def write_poses_h5(data: PoseData, path: str | Path) -> None:
    """Write ``poses.h5`` atomically (temporary name, then rename)."""
    with atomic_h5(path) as f:
        write_poses_group(f, data)


def write_poses_group(f: h5py.Group, data: PoseData) -> None:
    """Write the schema into an open HDF5 file or group (used by incremental writers)."""
    f.attrs["schema"] = SCHEMA
    f.attrs["schema_version"] = SCHEMA_VERSION
    f.create_dataset("poses", data=data.poses, compression="gzip", compression_opts=4)
    f.create_dataset("confidence", data=data.confidence, compression="gzip", compression_opts=4)
    f.create_dataset("keypoints", data=str_array(data.keypoints))
    f.create_dataset("frame_index", data=data.frame_index)
    if data.individuals is not None:
        f.create_dataset("individuals", data=str_array(data.individuals))
    if data.identity_confidence is not None:
        f.create_dataset("identity_confidence", data=data.identity_confidence)
    f.attrs["fps"] = data.fps
    f.attrs["units"] = "mm"
    f.attrs["up"] = data.up
    f.attrs["freipose_version"] = __version__
    if data.calibration is not None:
        f.attrs["calibration"] = rig_to_toml_text(data.calibration)
    if data.skeleton is not None:
        f.attrs["skeleton"] = tomli_w.dumps(data.skeleton.to_dict())
    if data.provenance:
        f.attrs["provenance"] = json.dumps(dict(data.provenance), default=str)
    if data.extra:
        g = f.create_group("extra")
        for k, v in data.extra.items():
            g.create_dataset(k, data=v, compression="gzip", compression_opts=4)


def write_movement_poses(data: PoseData, path: str | Path) -> Path:
    """Write ``data`` as a movement poses dataset (netCDF ``.nc``, see ``freipose.io.movement``).

    Raises:
        MovementFormatError: xarray or a netCDF engine is missing.
    """
    attrs: dict[str, Any] = {"up": data.up}
    if data.calibration is not None:
        attrs["calibration"] = rig_to_toml_text(data.calibration)
    if data.skeleton is not None:
        attrs["skeleton"] = tomli_w.dumps(data.skeleton.to_dict())
    if data.provenance:
        attrs["provenance"] = json.dumps(dict(data.provenance), default=str)
    arrays = MovementPoses(
        data.poses, data.confidence, data.keypoints, data.frame_index, data.fps, attrs,
        data.individuals, data.identity_confidence,
    )  # fmt: skip
    return write_movement(path, arrays)


def _read_movement_poses(path: Path) -> PoseData:
    """A movement poses dataset (``.nc``) as :class:`PoseData`."""
    m = read_movement(path)
    try:
        calib = (
            rig_from_toml_text(str(m.attrs["calibration"]), f"{path}:calibration")
            if "calibration" in m.attrs
            else None
        )
        skel = None
        if "skeleton" in m.attrs:
            where = f"{path}:skeleton"
            text = str(m.attrs["skeleton"])
            skel = skeleton_from_dict(parse_toml(text, where, "skeleton", PosesFormatError), where)
        prov = json.loads(str(m.attrs["provenance"])) if "provenance" in m.attrs else {}
        return PoseData(
            poses=m.poses,
            confidence=m.confidence,
            keypoints=m.keypoints,
            frame_index=m.frame_index,
            fps=m.fps,
            up=np.asarray(m.attrs.get("up", [0.0, 0.0, 1.0])),
            calibration=calib,
            skeleton=skel,
            provenance=prov,
            individuals=m.individuals,
            identity_confidence=m.identity_confidence,
        )
    except ValueError as exc:
        if isinstance(exc, PosesFormatError):
            raise
        raise PosesFormatError(f"{path}: {exc}") from exc


def read_poses_h5(path: str | Path, require_up: bool = True) -> PoseData:
    """Read and validate ``poses.h5``, or a movement poses dataset (suffix ``.nc``).

    Raises:
        PosesFormatError: the file is not a valid poses file (the message says why).
        MovementFormatError: a ``.nc`` file is not a movement poses dataset, or xarray
            is not installed.
        FileNotFoundError: the file does not exist.
    """
    path = Path(path)
    if path.suffix == MOVEMENT_SUFFIX:
        return _read_movement_poses(path)
    with open_h5(path, "poses file", PosesFormatError) as f:
        missing = [d for d in ("poses", "confidence", "keypoints", "frame_index") if d not in f]
        if missing:
            raise PosesFormatError(
                f"{path}: missing datasets {missing}; a poses file needs poses (T,K,3), "
                f"confidence (T,K), keypoints (K,) and frame_index (T,)"
            )
        if "fps" not in f.attrs:
            raise PosesFormatError(f"{path}: missing the 'fps' attribute")
        if require_up and "up" not in f.attrs:
            raise PosesFormatError(
                f"{path}: missing the 'up' attribute (the world up vector); re-export the poses "
                f"with FreiPose or add it, e.g. h5py.File(path, 'a').attrs['up'] = [0, 0, 1]"
            )
        units = str(f.attrs.get("units", "mm"))
        if units != "mm":
            raise PosesFormatError(f"{path}: units are {units!r}; FreiPose poses are in 'mm'")
        try:
            calib = (
                rig_from_toml_text(f.attrs["calibration"], f"{path}:calibration")
                if "calibration" in f.attrs
                else None
            )
            skel = None
            if "skeleton" in f.attrs:
                where = f"{path}:skeleton"
                text = f.attrs["skeleton"]
                skel = skeleton_from_dict(
                    parse_toml(text, where, "skeleton", PosesFormatError), where
                )
            prov = json.loads(f.attrs["provenance"]) if "provenance" in f.attrs else {}
            extra = {k: f["extra"][k][()] for k in f["extra"]} if "extra" in f else {}
            animals = tuple(decode_strings(f["individuals"][()])) if "individuals" in f else None
            ident = f["identity_confidence"][()] if "identity_confidence" in f else None
            return PoseData(
                poses=f["poses"][()],
                confidence=f["confidence"][()],
                keypoints=tuple(decode_strings(f["keypoints"][()])),
                frame_index=f["frame_index"][()],
                fps=float(f.attrs["fps"]),
                up=np.asarray(f.attrs.get("up", [0.0, 0.0, 1.0])),
                calibration=calib,
                skeleton=skel,
                provenance=prov,
                extra=extra,
                individuals=animals,
                identity_confidence=ident,
            )
        except ValueError as exc:
            if isinstance(exc, PosesFormatError) and str(exc).startswith(str(path)):
                raise
            raise PosesFormatError(f"{path}: {exc}") from exc
        except OSError as exc:  # a dataset whose data lies beyond a truncated end
            raise PosesFormatError(
                f"{path}: data cannot be read ({exc}); is the file truncated?"
            ) from exc


class IncompletePosesError(FreiPoseError):
    """A poses file whose prediction run has not finished (``complete`` is false)."""


PARTIAL_SUFFIX = ".partial"


@dataclass(frozen=True)
class RunState:
    """How far the prediction run that writes a poses file has come.

    Attributes:
        done: frames with a final prediction (``completed_frames``).
        total: rows of the file.
        complete: the run has finished (no ``complete`` attribute counts as finished).
        provenance: the run's provenance (session, model, detection settings).
        frames: the run's frame range ``(start, stop)`` (all shards).
        shard: ``"I/N"`` for a shard file, else ``""``.
    """

    done: int
    total: int
    complete: bool
    provenance: Mapping[str, Any]
    frames: tuple[int, int]
    shard: str = ""

    @property
    def missing(self) -> int:
        """Frames without a prediction yet."""
        return self.total - self.done


def run_state(path: str | Path) -> RunState:
    """The :class:`RunState` of the poses file ``path`` (a ``.partial`` file too).

    A file without a ``complete`` attribute (written in one go by :func:`write_poses_h5` or
    another tool) is complete unless its name ends in ``.partial``.

    Raises:
        PosesFormatError: the file is not a readable poses file.
    """
    path = Path(path)
    with open_h5(path, "poses file", PosesFormatError) as f:
        total = int(f["poses"].shape[0]) if "poses" in f else 0  # read_poses_h5 says more
        partial = path.name.endswith(PARTIAL_SUFFIX)
        complete = bool(f.attrs.get("complete", not partial))
        if "completed_frames" in f.attrs:
            done = int(f.attrs["completed_frames"])
        elif "extra/status" in f:  # status -1: not predicted yet
            done = int((f["extra/status"][()] >= 0).sum())
        else:
            done = total if complete else 0
        fi = f["frame_index"][()] if "frame_index" in f else np.zeros(0, np.int64)
        frames = (int(fi[0]), int(fi[-1]) + 1) if len(fi) else (0, 0)
        if "run_range" in f.attrs:
            rr = f.attrs["run_range"]
            frames = (int(rr[0]), int(rr[1]))
        try:
            prov = json.loads(f.attrs["provenance"]) if "provenance" in f.attrs else {}
        except ValueError:
            prov = {}
        shard = str(f.attrs.get("shard", ""))
    return RunState(done, total, complete, prov if isinstance(prov, dict) else {}, frames, shard)


def resume_command(path: str | Path, state: RunState) -> str:
    """The ``freipose predict`` command that finishes the run writing ``path``.

    Built from the provenance the run stored (session, model and detection settings); the
    parts it does not record appear as placeholders (``SESSION``, ``...``).
    """
    prov = state.provenance
    path = Path(path)
    name = path.name[: -len(PARTIAL_SUFFIX)] if path.name.endswith(PARTIAL_SUFFIX) else path.name
    parts = ["freipose predict", str(prov.get("session", "SESSION"))]
    parts.append(f"--model {prov.get('model_file', '...')}")
    method = prov.get("detection")
    if method == "detector":
        parts.append(f"--detector {prov.get('detector_file', 'DETECTOR')}")
    elif method == "bgsub":
        parts.append("--method bgsub")
        if int(prov.get("bg_samples", 40)) != 40:
            parts.append(f"--bg-samples {int(prov['bg_samples'])}")
    elif method == "fixed":
        parts.append("--fixed-boxes BOXES.toml")
    if "min_views" in prov and int(prov["min_views"]) != 2:
        parts.append(f"--min-views {int(prov['min_views'])}")
    if prov.get("refine") is False:
        parts.append("--no-refine")
    if int(prov.get("animals", 1)) > 1:
        parts.append(f"--animals {int(prov['animals'])}")
    if "session" in prov:
        parts.append(f"--frames {state.frames[0]}:{state.frames[1]}")
    if state.shard:
        parts.append(f"--shard {state.shard}")
    outdir = path.parent if name.endswith(".poses.h5") else Path("DIR")
    parts.append(f"-o {outdir}")
    return " ".join(parts)


def require_complete(path: str | Path, allow_incomplete: bool = False) -> int:
    """Refuse a poses file whose prediction run has not finished, unless allowed.

    Args:
        path: the poses file (``<session>.poses.h5`` or its ``.partial`` file).
        allow_incomplete: go on with an unfinished file (its missing frames hold NaN).

    Returns:
        The number of frames without a prediction (0 for a complete file).

    Raises:
        IncompletePosesError: the file is unfinished and ``allow_incomplete`` is false; the
            message names the frames predicted and the command that finishes the run.
        PosesFormatError: the file is not a readable poses file.
    """
    state = run_state(path)
    if state.complete:
        return 0
    if not allow_incomplete:
        raise IncompletePosesError(
            f"{path} is incomplete ({state.done} of {state.total} frames predicted): finish "
            f"it with `{resume_command(path, state)}` (it resumes), or pass "
            f"--allow-incomplete to go on without the {state.missing} missing frames"
        )
    return state.missing
