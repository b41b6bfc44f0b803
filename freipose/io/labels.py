"""Labeled datasets ``labels.h5`` (schema in ``docs/formats.md``).

N labeled time instants over V cameras and K keypoints:

* ``session`` (N,) UTF-8, ``frame_index`` (N,) int64: which recording and video frame;
* ``points2d`` (N, V, K, 2) float64 original-image pixels, NaN = unlabeled;
* ``points3d`` (N, K, 3) float64 world mm, NaN = unknown;
* ``visible2d`` (N, V, K) bool, optional: the keypoint is visible (not occluded, inside the
  image) in that view; absent means "labeled implies visible";
* ``individual`` (N,) UTF-8, optional: the animal of each row; the rows of one session and
  frame with different individuals are the animals of that instant, and one name is one
  animal across the frames of its session; absent means one animal per row;
* ``cameras`` (V,) and ``keypoints`` (K,) UTF-8 names;
* group ``sessions/<name>`` per session: attribute ``calibration`` (calibration.toml
  text, may be absent for 2D-only data), attribute ``videos`` (JSON: camera name -> video
  path, relative to the labels file), attribute ``fps`` (optional), attribute
  ``instances`` (optional: which SLEAP instances were imported, ``user``/``predicted``/``all``).

Sessions may use different rigs: the camera axis is the union of camera names, and a
camera that a session lacks has NaN labels there.
"""

from __future__ import annotations

import contextlib
import json
import shlex
import socket
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType

import h5py
import numpy as np

from freipose import __version__
from freipose._frozen import PicklableFrozen
from freipose.errors import FreiPoseError
from freipose.geometry.camera import CameraRig
from freipose.io.atomic import atomic_h5
from freipose.io.calibration_toml import rig_from_toml_text, rig_to_toml_text
from freipose.io.hdf5 import decode_strings, open_h5, str_array
from freipose.io.lock import OutputLockedError, lock_path, output_lock

SCHEMA = "freipose.labels"
SCHEMA_VERSION = 1


class LabelsFormatError(FreiPoseError):
    """A labels file is malformed; the message names the file and the problem."""


@dataclass(frozen=True, eq=False)
class SessionInfo(PicklableFrozen):
    """Per-session facts: cameras, videos (camera name -> path), frame rate, instances.

    ``instances`` says which instances of the source were imported (SLEAP: ``user``,
    ``predicted`` or ``all``; None for other sources).
    """

    calibration: CameraRig | None = None
    videos: Mapping[str, str] = field(default_factory=dict)
    fps: float | None = None
    instances: str | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "videos", MappingProxyType(dict(self.videos)))


@dataclass(frozen=True, eq=False)
class LabelSet(PicklableFrozen):
    """A labeled dataset (see the module docstring for shapes)."""

    session: np.ndarray
    frame_index: np.ndarray
    points2d: np.ndarray
    points3d: np.ndarray
    cameras: tuple[str, ...]
    keypoints: tuple[str, ...]
    sessions: Mapping[str, SessionInfo] = field(default_factory=dict)
    visible2d: np.ndarray | None = None
    individual: np.ndarray | None = None

    def __post_init__(self) -> None:
        sess = np.asarray([str(s) for s in np.asarray(self.session).reshape(-1)], dtype=object)
        n = len(sess)
        fi = np.asarray(self.frame_index, dtype=np.int64).reshape(-1)
        cams = tuple(str(c) for c in self.cameras)
        kps = tuple(str(k) for k in self.keypoints)
        v, k = len(cams), len(kps)
        p2 = np.asarray(self.points2d, dtype=np.float64)
        p3 = np.asarray(self.points3d, dtype=np.float64)
        if fi.shape != (n,):
            raise LabelsFormatError(f"frame_index must have shape ({n},), got {fi.shape}")
        if p2.shape != (n, v, k, 2):
            raise LabelsFormatError(f"points2d must have shape {(n, v, k, 2)}, got {p2.shape}")
        if p3.shape != (n, k, 3):
            raise LabelsFormatError(f"points3d must have shape {(n, k, 3)}, got {p3.shape}")
        if len(set(cams)) != v or len(set(kps)) != k:
            raise LabelsFormatError("camera names and keypoint names must be unique")
        vis = None
        if self.visible2d is not None:
            vis = np.asarray(self.visible2d, dtype=bool)
            if vis.shape != (n, v, k):
                raise LabelsFormatError(f"visible2d must have shape {(n, v, k)}, got {vis.shape}")
        ind = None
        if self.individual is not None:
            ind = np.asarray([str(a) for a in np.asarray(self.individual).reshape(-1)], object)
            if ind.shape != (n,):
                raise LabelsFormatError(f"individual must have shape ({n},), got {ind.shape}")
        infos = dict(self.sessions)
        for s in sorted(set(sess)):
            infos.setdefault(s, SessionInfo())
        for s, info in infos.items():
            if info.calibration is not None:
                extra = [c for c in info.calibration.names if c not in cams]
                if extra:
                    raise LabelsFormatError(
                        f"session {s!r}: calibration cameras {extra} not in cameras {list(cams)}"
                    )
        object.__setattr__(self, "session", sess)
        object.__setattr__(self, "frame_index", fi)
        object.__setattr__(self, "points2d", p2)
        object.__setattr__(self, "points3d", p3)
        object.__setattr__(self, "cameras", cams)
        object.__setattr__(self, "keypoints", kps)
        object.__setattr__(self, "visible2d", vis)
        object.__setattr__(self, "individual", ind)
        object.__setattr__(self, "sessions", MappingProxyType(infos))

    def __len__(self) -> int:
        return len(self.session)

    def select(self, mask_or_index: np.ndarray | Sequence[int]) -> LabelSet:
        """A subset of the time instants (boolean mask or indices)."""
        idx = np.asarray(mask_or_index)
        if idx.dtype == bool:
            idx = np.flatnonzero(idx)
        keep = {str(s) for s in self.session[idx]}
        return LabelSet(
            self.session[idx],
            self.frame_index[idx],
            self.points2d[idx],
            self.points3d[idx],
            self.cameras,
            self.keypoints,
            {s: i for s, i in self.sessions.items() if s in keep},
            None if self.visible2d is None else self.visible2d[idx],
            None if self.individual is None else self.individual[idx],
        )

    @property
    def individuals(self) -> tuple[str, ...]:
        """The animals' names in order of appearance (``()`` without ``individual``)."""
        if self.individual is None:
            return ()
        return tuple(dict.fromkeys(str(a) for a in self.individual))

    def rig_for(self, session: str) -> CameraRig | None:
        """The calibration of ``session`` (None for 2D-only data)."""
        info = self.sessions.get(session)
        return None if info is None else info.calibration


@contextlib.contextmanager
def labels_file_lock(
    path: str | Path, what: str = "labels file", option: str = "-o"
) -> Iterator[Path]:
    """Hold the lock of the labels file ``path`` (taken on its real path) during the block.

    Every writer of a labels file holds it: the ``freipose label`` server for as long as it
    runs, the ``freipose labels`` commands while they write. A symbolic link and its target
    share one lock, and the block writes to the yielded real path, so that a link stays a
    link.

    Args:
        path: the labels file (or another output that may be one, such as ``-o`` of
            ``labels boxes``).
        what: what the output is, for the log.
        option: the command's option that names another output, for the refusal.

    Yields:
        The real path of ``path`` (symbolic links resolved), to write to.

    Raises:
        OutputLockedError: another run holds the lock; the message names its command.
    """
    real = Path(path).resolve()
    stack = contextlib.ExitStack()
    try:
        stack.enter_context(output_lock(real, what, option))
    except OutputLockedError as exc:
        raise _in_use(exc, real, option) from None
    with stack:
        yield real


def _short(command: str) -> str:
    """A command line with its program named by its file name (``freipose label ...``)."""
    try:
        words = shlex.split(command)
    except ValueError:
        return command
    return shlex.join([Path(words[0]).name, *words[1:]]) if words else command


def _in_use(exc: OutputLockedError, real: Path, option: str) -> OutputLockedError:
    """The refusal of a labels file in use, naming the command that holds it."""
    o = exc.owner
    if o is None:
        return exc
    msg = (
        f"{real} is in use by another run: `{_short(o.command)}` ({o.host}, pid {o.pid}, started "
        f"{o.started}); wait for that run to end or stop it (a `freipose label` server "
        f"stops with Ctrl-C in its terminal, every edit saved), or pass another {option}"
    )
    if o.host != socket.gethostname():
        msg += f"; if that run is gone, delete {lock_path(real)}"
    return OutputLockedError(msg, o)


def write_labels_h5(labels: LabelSet, path: str | Path, *, lock: bool = True) -> None:
    """Write ``labels.h5`` atomically, holding its :func:`labels_file_lock`.

    Args:
        labels: the labels.
        path: the file (a symbolic link is written through).
        lock: take the lock; False only when the caller holds it already (a command that
            took it before its work).

    Raises:
        OutputLockedError: another run (a ``freipose label`` server) writes the file.
    """
    held = labels_file_lock(path) if lock else contextlib.nullcontext(Path(path).resolve())
    with held as real, atomic_h5(real) as f:
        fill_labels_h5(f, labels)


def fill_labels_h5(f: h5py.File, labels: LabelSet) -> None:
    """Write the datasets of ``labels`` into the open, empty HDF5 file ``f``.

    Only for a writer that holds the file's :func:`labels_file_lock` and writes to a
    temporary name (the ``freipose label`` server); others call :func:`write_labels_h5`.
    """
    f.attrs["schema"] = SCHEMA
    f.attrs["schema_version"] = SCHEMA_VERSION
    f.attrs["units"] = "mm"
    f.attrs["freipose_version"] = __version__
    f.create_dataset("session", data=str_array(labels.session))
    f.create_dataset("frame_index", data=labels.frame_index)
    f.create_dataset("points2d", data=labels.points2d, compression="gzip")
    f.create_dataset("points3d", data=labels.points3d, compression="gzip")
    if labels.visible2d is not None:
        f.create_dataset("visible2d", data=labels.visible2d, compression="gzip")
    if labels.individual is not None:
        f.create_dataset("individual", data=str_array(labels.individual))
    f.create_dataset("cameras", data=str_array(labels.cameras))
    f.create_dataset("keypoints", data=str_array(labels.keypoints))
    g = f.create_group("sessions")
    for name, info in labels.sessions.items():
        sg = g.create_group(name)
        if info.calibration is not None:
            sg.attrs["calibration"] = rig_to_toml_text(info.calibration)
        sg.attrs["videos"] = json.dumps(dict(info.videos))
        if info.fps is not None:
            sg.attrs["fps"] = float(info.fps)
        if info.instances is not None:
            sg.attrs["instances"] = str(info.instances)


def read_labels_h5(path: str | Path) -> LabelSet:
    """Read and validate ``labels.h5``.

    Raises:
        LabelsFormatError: the file is not a valid labels file (the message says why).
        FileNotFoundError: the file does not exist.
    """
    path = Path(path)
    with open_h5(path, "labels file", LabelsFormatError) as f:
        need = ["session", "frame_index", "points2d", "points3d", "cameras", "keypoints"]
        missing = [d for d in need if d not in f]
        if missing:
            raise LabelsFormatError(
                f"{path}: missing datasets {missing}; see docs/formats.md (labels.h5)"
            )
        try:
            sessions = {}
            if "sessions" in f:
                for name, sg in f["sessions"].items():
                    cal = sg.attrs.get("calibration")
                    sessions[name] = SessionInfo(
                        rig_from_toml_text(cal, f"{path}:sessions/{name}")
                        if cal is not None
                        else None,
                        json.loads(sg.attrs.get("videos", "{}")),
                        float(sg.attrs["fps"]) if "fps" in sg.attrs else None,
                        str(sg.attrs["instances"]) if "instances" in sg.attrs else None,
                    )
            return LabelSet(
                np.array(decode_strings(f["session"][()]), dtype=object),
                f["frame_index"][()],
                f["points2d"][()],
                f["points3d"][()],
                tuple(decode_strings(f["cameras"][()])),
                tuple(decode_strings(f["keypoints"][()])),
                sessions,
                f["visible2d"][()] if "visible2d" in f else None,
                np.array(decode_strings(f["individual"][()]), dtype=object)
                if "individual" in f
                else None,
            )
        except (ValueError, KeyError) as exc:
            if isinstance(exc, LabelsFormatError):
                raise
            raise LabelsFormatError(f"{path}: {exc}") from exc
        except OSError as exc:  # a dataset whose data lies beyond a truncated end
            raise LabelsFormatError(
                f"{path}: data cannot be read ({exc}); is the file truncated?"
            ) from exc
