"""Incremental, resumable writer of ``poses.h5`` (the schema of ``freipose.io.poses``).

The output is written to ``<name>.poses.h5.partial``: all datasets are created at their
full size up front (NaN / confidence 0 / status -1), and predictions are written one chunk
of rows at a time; after each chunk the attribute ``completed_frames`` records how many
leading rows are final. A killed run restarted with the same settings reopens the partial
file and continues after ``completed_frames``; when all rows are written the attribute
``complete`` is set to true and the file is renamed to ``<name>.poses.h5``.

A partial file written with different settings (another model, calibration, frame range
or shard) is discarded with a warning, as is one that cannot be opened (killed while HDF5
was writing its metadata).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import tomli_w

from freipose import __version__
from freipose.geometry.camera import CameraRig
from freipose.io.calibration_toml import rig_to_toml_text
from freipose.io.calibration_world import WorldUp
from freipose.io.hdf5 import str_array
from freipose.io.poses import SCHEMA, SCHEMA_VERSION
from freipose.predict.estimator import Estimate
from freipose.skeleton import Skeleton

log = logging.getLogger(__name__)

PARTIAL_SUFFIX = ".partial"

# extra/status codes
STATUS_PENDING = -1  #: not predicted yet (only in partial files)
STATUS_OK = 0  #: predicted
STATUS_NOT_FOUND = 1  #: the animal was not found (no detection / no finite keypoint)
STATUS_FEW_VIEWS = 2  #: fewer than two cameras' frames could be decoded

_COMPRESSION = {"compression": "gzip", "compression_opts": 4}


@dataclass(frozen=True, eq=False)
class OutputHeader:
    """Everything about an output file except the predictions.

    Attributes:
        keypoints: (K,) names.
        rig: the cameras (C) whose per-view results are stored.
        start, stop: frame range of this file (``frame_index = arange(start, stop)``).
        fps: frame rate.
        skeleton: the model's skeleton (optional).
        provenance: JSON-able facts (model hash, videos, FreiPose version, settings).
        up: world up vector.
        run_start, run_stop: frame range of the whole (unsharded) run.
        shard: (index, count) when this file is one shard of a run.
    """

    keypoints: tuple[str, ...]
    rig: CameraRig
    start: int
    stop: int
    fps: float
    skeleton: Skeleton | None = None
    provenance: Mapping[str, Any] = field(default_factory=dict)
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    run_start: int | None = None
    run_stop: int | None = None
    shard: tuple[int, int] | None = None

    @property
    def num_frames(self) -> int:
        """Rows of this output (``stop - start``)."""
        return self.stop - self.start

    @property
    def run_range(self) -> tuple[int, int]:
        """The frame range ``(start, stop)`` of the whole run (all shards)."""
        a = self.start if self.run_start is None else self.run_start
        b = self.stop if self.run_stop is None else self.run_stop
        return a, b

    def calibration_text(self) -> str:
        """The rig as ``calibration.toml`` text."""
        return rig_to_toml_text(self.rig)

    def skeleton_text(self) -> str | None:
        """The skeleton as TOML text, or None."""
        return tomli_w.dumps(self.skeleton.to_dict()) if self.skeleton is not None else None

    def provenance_text(self) -> str:
        """The provenance as JSON text (sorted keys)."""
        return json.dumps(dict(self.provenance), default=str, sort_keys=True)

    def run_key(self) -> str:
        """A hash of the settings that determine the predictions of the whole run."""
        doc = {
            "keypoints": list(self.keypoints),
            "calibration": self.calibration_text(),
            "skeleton": self.skeleton_text(),
            "provenance": self.provenance_text(),
            "range": list(self.run_range),
            "fps": float(self.fps),
            "up": [float(u) for u in self.up],
        }
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()

    def shard_text(self) -> str:
        """``"I/N"``, or ``""`` for an unsharded run."""
        return "" if self.shard is None else f"{self.shard[0]}/{self.shard[1]}"


def partial_path(path: str | Path) -> Path:
    """Where the unfinished output of ``path`` is written."""
    path = Path(path)
    return path.with_name(path.name + PARTIAL_SUFFIX)


def is_complete(path: str | Path) -> bool:
    """True if ``path`` is a poses file whose ``complete`` attribute is set."""
    path = Path(path)
    if not path.is_file():
        return False
    try:
        with h5py.File(path, "r") as f:
            return bool(f.attrs.get("complete", False))
    except OSError:
        return False


def create_layout(f: h5py.File, header: OutputHeader, chunk_rows: int) -> None:
    """Create the attributes and the full-size, chunked datasets of an empty output."""
    T, K, C = header.num_frames, len(header.keypoints), len(header.rig)
    ch = max(1, min(chunk_rows, T))
    f.attrs["schema"] = SCHEMA
    f.attrs["schema_version"] = SCHEMA_VERSION
    f.attrs["fps"] = float(header.fps)
    f.attrs["units"] = "mm"
    up = np.asarray(header.up, np.float64)
    f.attrs["up"] = up / np.linalg.norm(up)
    f.attrs["freipose_version"] = __version__
    f.attrs["calibration"] = header.calibration_text()
    skel = header.skeleton_text()
    if skel is not None:
        f.attrs["skeleton"] = skel
    f.attrs["provenance"] = header.provenance_text()
    f.attrs["run_key"] = header.run_key()
    if header.shard is not None:
        f.attrs["shard"] = header.shard_text()
        f.attrs["run_range"] = np.asarray(header.run_range, np.int64)
    f.attrs["completed_frames"] = 0
    f.attrs["complete"] = False
    nan = np.float32(np.nan)

    def ds(g: h5py.Group, name: str, shape: tuple, dtype: Any, fill: Any) -> None:
        g.create_dataset(
            name, shape=shape, dtype=dtype, chunks=(ch, *shape[1:]), fillvalue=fill, **_COMPRESSION
        )

    ds(f, "poses", (T, K, 3), np.float32, nan)
    ds(f, "confidence", (T, K), np.float32, np.float32(0))
    f.create_dataset("keypoints", data=str_array(header.keypoints))
    f.create_dataset("frame_index", data=np.arange(header.start, header.stop, dtype=np.int64))
    g = f.create_group("extra")
    ds(g, "points2d", (T, C, K, 2), np.float32, nan)
    ds(g, "confidence2d", (T, C, K), np.float32, np.float32(0))
    ds(g, "boxes", (T, C, 4), np.float32, nan)
    ds(g, "center", (T, 3), np.float32, nan)
    ds(g, "status", (T,), np.int8, np.int8(STATUS_PENDING))
    ds(g, "frame_ok", (T, C), bool, False)
    g.attrs["cameras"] = json.dumps(header.rig.names)


ROW_FIELDS = (
    "poses",
    "confidence",
    "points2d",
    "confidence2d",
    "boxes",
    "center",
    "status",
    "frame_ok",
)
_PATHS = {
    "poses": "poses",
    "confidence": "confidence",
    **{
        n: f"extra/{n}"
        for n in ("points2d", "confidence2d", "boxes", "center", "status", "frame_ok")
    },
}


class IncrementalPosesWriter:
    """Write the rows of one output file in order, resumably.

    Args:
        path: final path (``.../<name>.poses.h5``); work happens in ``path + ".partial"``.
        header: the file's settings.
        chunk_rows: rows per HDF5 chunk and per commit (a kill loses at most this many).

    Usage::

        w = IncrementalPosesWriter(path, header, 256)
        done = w.open()            # rows already final (resume point)
        w.add(estimate, status, frame_ok)   # rows done, done+1, ... in order
        w.finish()                 # -> path
    """

    def __init__(self, path: str | Path, header: OutputHeader, chunk_rows: int = 256):
        if chunk_rows < 1:
            raise ValueError(f"chunk_rows must be positive, got {chunk_rows}")
        self.path = Path(path)
        self.partial = partial_path(self.path)
        self.header = header
        self.chunk_rows = int(chunk_rows)
        self._f: h5py.File | None = None
        self._buf: dict[str, list[np.ndarray]] = {k: [] for k in ROW_FIELDS}
        self._buffered = 0
        self.completed = 0

    # -- open / resume --------------------------------------------------------------------
    def _try_resume(self) -> h5py.File | None:
        if not self.partial.exists():
            return None
        try:
            f = h5py.File(self.partial, "a")
        except OSError as exc:
            log.warning("%s cannot be opened (%s); starting this output again", self.partial, exc)
            return None
        key = str(f.attrs.get("run_key", ""))
        shard = str(f.attrs.get("shard", ""))
        T = f["poses"].shape[0] if "poses" in f else -1
        if (
            key != self.header.run_key()
            or shard != self.header.shard_text()
            or self.header.num_frames != T
        ):
            log.warning(
                "%s was written with other settings (model, calibration, frames or shard); "
                "starting this output again",
                self.partial,
            )
            f.close()
            return None
        return f

    def open(self) -> int:
        """Open (resume or create) the partial file; returns the number of final rows."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        f = self._try_resume()
        if f is not None:
            self.completed = int(f.attrs.get("completed_frames", 0))
            if self.completed:
                log.info(
                    "%s: resuming after %d of %d frames",
                    self.partial,
                    self.completed,
                    self.header.num_frames,
                )
        else:
            self.partial.unlink(missing_ok=True)
            f = h5py.File(self.partial, "w")
            create_layout(f, self.header, self.chunk_rows)
            f.flush()
            self.completed = 0
        self._f = f
        return self.completed

    # -- writing --------------------------------------------------------------------------
    def add(self, est: Estimate, status: np.ndarray, frame_ok: np.ndarray) -> None:
        """Append the next ``B`` rows (B = ``est.batch_size``)."""
        if self._f is None:
            raise RuntimeError("IncrementalPosesWriter.add before open()")
        B = est.batch_size
        if self.completed + self._buffered + B > self.header.num_frames:
            raise ValueError(
                f"writing {B} rows after {self.completed + self._buffered} overflows the "
                f"{self.header.num_frames}-frame output"
            )
        vals = {
            "poses": est.poses,
            "confidence": est.confidence,
            "points2d": est.points2d,
            "confidence2d": est.confidence2d,
            "boxes": est.boxes,
            "center": est.center,
            "status": np.asarray(status, np.int8).reshape(B),
            "frame_ok": np.asarray(frame_ok, bool).reshape(B, -1),
        }
        for k, v in vals.items():
            self._buf[k].append(v)
        self._buffered += B
        # commit whole chunks (aligned to row 0 of the file)
        while self._buffered:
            boundary = (self.completed // self.chunk_rows + 1) * self.chunk_rows
            boundary = min(boundary, self.header.num_frames)
            if self.completed + self._buffered < boundary:
                break
            self._commit(boundary - self.completed)

    def _commit(self, n: int) -> None:
        assert self._f is not None
        a = self.completed
        rest: dict[str, list[np.ndarray]] = {}
        for k in ROW_FIELDS:
            arr = np.concatenate(self._buf[k], axis=0)
            self._f[_PATHS[k]][a : a + n] = arr[:n]
            rest[k] = [arr[n:]] if len(arr) > n else []
        self._buf = rest
        self._buffered -= n
        self._f.flush()
        self.completed = a + n
        self._f.attrs["completed_frames"] = self.completed
        self._f.flush()

    def poses(self) -> np.ndarray:
        """(T, K, 3) the poses committed so far (NaN in rows not yet written)."""
        if self._f is None:
            raise RuntimeError("IncrementalPosesWriter.poses before open()")
        return self._f["poses"][()]

    def finish(self, up: WorldUp | None = None) -> Path:
        """Write what is buffered, mark the file complete and move it to its final name.

        Args:
            up: the world up found once all rows are in (the ``up`` and ``up_source``
                attributes; the header's up, and the run key, stay as they were), or None
                to keep the header's.
        """
        if self._f is None:
            raise RuntimeError("IncrementalPosesWriter.finish before open()")
        if self._buffered:
            self._commit(self._buffered)
        if self.completed != self.header.num_frames:
            raise RuntimeError(
                f"{self.partial}: only {self.completed} of {self.header.num_frames} rows written"
            )
        if up is not None:
            self._f.attrs["up"] = up.up
            self._f.attrs["up_source"] = up.source
        self._f.attrs["complete"] = True
        self._f.close()
        self._f = None
        os.replace(self.partial, self.path)
        return self.path

    def close(self) -> None:
        """Close without finishing (rows of unfinished chunks are discarded; resume redoes them)."""
        if self._f is not None:
            self._f.close()
            self._f = None

    def __enter__(self) -> IncrementalPosesWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
