"""The layout of a ``poses.h5`` output: its settings, its datasets and the room it takes.

:class:`OutputHeader` holds everything about an output except the predictions;
:func:`create_layout` creates every dataset at its full size up front (NaN, confidence 0,
``extra/status`` :data:`STATUS_PENDING`); :func:`output_bytes` bounds the file's size and
:func:`check_free_space` refuses to write what the disk cannot hold.
:class:`~freipose.predict.writer.IncrementalPosesWriter` fills such a file row by row.
"""

from __future__ import annotations

import errno
import hashlib
import json
import shutil
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import tomli_w

from freipose import __version__
from freipose.errors import OutputWriteError, bytes_text
from freipose.geometry.camera import CameraRig
from freipose.io.calibration_toml import rig_to_toml_text
from freipose.io.hdf5 import str_array
from freipose.io.poses import SCHEMA, SCHEMA_VERSION
from freipose.skeleton import Skeleton

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
        individuals: (A,) the animals of an output with an animal axis; None: one animal.
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
    individuals: tuple[str, ...] | None = None

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
        if self.individuals is not None:  # one animal: the key it always had
            doc["individuals"] = list(self.individuals)
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()

    def shard_text(self) -> str:
        """``"I/N"``, or ``""`` for an unsharded run."""
        return "" if self.shard is None else f"{self.shard[0]}/{self.shard[1]}"


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
        if T == 0:  # an empty shard: HDF5 chunks cannot be empty
            g.create_dataset(name, shape=shape, dtype=dtype, fillvalue=fill)
            return
        g.create_dataset(
            name, shape=shape, dtype=dtype, chunks=(ch, *shape[1:]), fillvalue=fill, **_COMPRESSION
        )

    a = () if header.individuals is None else (len(header.individuals),)  # the animal axis
    ds(f, "poses", (T, *a, K, 3), np.float32, nan)
    ds(f, "confidence", (T, *a, K), np.float32, np.float32(0))
    f.create_dataset("keypoints", data=str_array(header.keypoints))
    f.create_dataset("frame_index", data=np.arange(header.start, header.stop, dtype=np.int64))
    if header.individuals is not None:
        f.create_dataset("individuals", data=str_array(header.individuals))
        ds(f, "identity_confidence", (T, *a), np.float32, nan)
    g = f.create_group("extra")
    if header.individuals is not None:
        ds(g, "identity_flagged", (T, *a), bool, False)
    ds(g, "points2d", (T, *a, C, K, 2), np.float32, nan)
    ds(g, "confidence2d", (T, *a, C, K), np.float32, np.float32(0))
    ds(g, "boxes", (T, *a, C, 4), np.float32, nan)
    ds(g, "center", (T, *a, 3), np.float32, nan)
    ds(g, "uncertainty", (T, *a, K), np.float32, nan)
    ds(g, "status", (T,), np.int8, np.int8(STATUS_PENDING))
    ds(g, "frame_ok", (T, C), bool, False)
    g.attrs["cameras"] = json.dumps(header.rig.names)


#: bytes beyond the datasets that an output may take (attributes, chunk indexes)
_OVERHEAD_BYTES = 64 * 1024


def output_bytes(header: OutputHeader) -> int:
    """At most how many bytes the output file of ``header`` takes (its data uncompressed)."""
    T, K, C = header.num_frames, len(header.keypoints), len(header.rig)
    A = 1 if header.individuals is None else len(header.individuals)
    floats = A * (3 * K + K + C * K * 2 + C * K + C * 4 + 3 + K + 1)
    row = 4 * floats + 1 + C + 8  # + status, frame_ok, frame_index
    text = len(header.calibration_text()) + len(header.provenance_text())
    return T * row + text + len(header.skeleton_text() or "") + _OVERHEAD_BYTES


def check_free_space(path: Path, needed: int, what: str = "it takes") -> None:
    """Refuse to start writing ``needed`` bytes in ``path``'s folder when it has fewer free.

    Args:
        path: the output.
        needed: bytes about to be written.
        what: what takes them, in the message ("it takes", "its next rows take").

    Raises:
        OutputWriteError: the disk holding ``path`` has less than ``needed`` bytes free.
    """
    free = shutil.disk_usage(path.parent).free
    if free < needed:
        raise OutputWriteError(
            f"cannot write {path}: {what} up to {bytes_text(needed)} and the disk holding "
            f"{path.parent.absolute()} has {bytes_text(free)} free; free space there (or "
            f"write to another folder) and run the command again",
            errno.ENOSPC,
            path,
        )
