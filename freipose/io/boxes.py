"""Per-frame boxes of the animal ``boxes.h5`` (written by ``freipose detect``).

T time instants over C cameras:

* ``frame_index`` (T,) int64 video frame numbers;
* ``cameras`` (C,) UTF-8 camera names (the calibration's order);
* ``boxes`` (T, C, 4) float64 ``(x0, y0, x1, y1)`` full-image pixels: the detector box
  that agreed with the 3D centre, else a replacement box around the projected centre; NaN
  where neither exists;
* ``scores`` (T, C) float32 the chosen box's detector score (0 for replacement boxes,
  NaN where there is no box);
* ``agree`` (T, C) bool: the view's box agreed with the 3D centre;
* ``n_agree`` (T,) int16: how many views agreed (0 = no 3D centre);
* ``center`` (T, 3) float64 world mm, NaN when fewer than ``min_views`` views agreed;
* ``crop_boxes`` (T, C, 4) float64 square boxes around the projected ``cube_size`` cube;
  NaN without a centre;
* root attributes ``schema = "freipose.boxes"``, ``schema_version``, ``units = "mm"``,
  ``freipose_version``, ``method`` (``detector``/``bgsub``/``fixed``), ``cube_size`` (mm),
  ``calibration`` (calibration.toml text), ``image_size`` (C, 2) width/height, ``source``
  (what produced the boxes, e.g. the checkpoint path).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

from freipose import __version__
from freipose.errors import FreiPoseError
from freipose.geometry.camera import CameraRig
from freipose.io.atomic import atomic_h5
from freipose.io.calibration_toml import rig_from_toml_text, rig_to_toml_text
from freipose.io.hdf5 import decode_strings, open_h5, str_array

SCHEMA = "freipose.boxes"
SCHEMA_VERSION = 1


class BoxesFormatError(FreiPoseError):
    """A boxes file is malformed; the message names the file and the problem."""


@dataclass(frozen=True, eq=False)
class BoxesData:
    """The contents of ``boxes.h5`` (see the module docstring for shapes)."""

    frame_index: np.ndarray
    cameras: tuple[str, ...]
    boxes: np.ndarray
    scores: np.ndarray
    agree: np.ndarray
    n_agree: np.ndarray
    center: np.ndarray
    crop_boxes: np.ndarray
    cube_size: float
    method: str
    calibration: CameraRig | None = None
    attrs: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        fi = np.asarray(self.frame_index, dtype=np.int64).reshape(-1)
        t = len(fi)
        cams = tuple(str(c) for c in self.cameras)
        c = len(cams)
        arrays = {
            "boxes": (np.float64, (t, c, 4)),
            "scores": (np.float32, (t, c)),
            "agree": (bool, (t, c)),
            "n_agree": (np.int16, (t,)),
            "center": (np.float64, (t, 3)),
            "crop_boxes": (np.float64, (t, c, 4)),
        }
        for name, (dt, shape) in arrays.items():
            a = np.asarray(getattr(self, name), dtype=dt)
            if a.shape != shape:
                raise BoxesFormatError(f"{name} must have shape {shape}, got {a.shape}")
            object.__setattr__(self, name, a)
        if self.calibration is not None and list(self.calibration.names) != list(cams):
            raise BoxesFormatError(
                f"calibration cameras {self.calibration.names} differ from cameras {list(cams)}"
            )
        object.__setattr__(self, "frame_index", fi)
        object.__setattr__(self, "cameras", cams)
        object.__setattr__(self, "cube_size", float(self.cube_size))
        object.__setattr__(self, "method", str(self.method))
        object.__setattr__(self, "attrs", MappingProxyType(dict(self.attrs)))

    def __len__(self) -> int:
        return len(self.frame_index)


def write_boxes_h5(data: BoxesData, path: str | Path) -> None:
    """Write ``boxes.h5`` atomically."""
    with atomic_h5(path) as f:
        f.attrs["schema"] = SCHEMA
        f.attrs["schema_version"] = SCHEMA_VERSION
        f.attrs["units"] = "mm"
        f.attrs["freipose_version"] = __version__
        f.attrs["method"] = data.method
        f.attrs["cube_size"] = data.cube_size
        if data.calibration is not None:
            f.attrs["calibration"] = rig_to_toml_text(data.calibration)
        for k, v in data.attrs.items():
            f.attrs[k] = v
        f.create_dataset("frame_index", data=data.frame_index)
        f.create_dataset("cameras", data=str_array(data.cameras))
        for name in ("boxes", "scores", "agree", "n_agree", "center", "crop_boxes"):
            f.create_dataset(name, data=getattr(data, name), compression="gzip")


def read_boxes_h5(path: str | Path) -> BoxesData:
    """Read and validate ``boxes.h5``.

    Raises:
        BoxesFormatError: not a valid boxes file (the message says why).
        FileNotFoundError: the file does not exist.
    """
    p = Path(path)
    with open_h5(p, "boxes file", BoxesFormatError) as f:
        schema = f.attrs.get("schema")
        if schema != SCHEMA:
            raise BoxesFormatError(
                f"{p}: expected a FreiPose boxes file (schema {SCHEMA!r}), found schema "
                f"{schema!r}; write one with `freipose detect`"
            )
        if int(f.attrs.get("schema_version", 0)) > SCHEMA_VERSION:
            raise BoxesFormatError(
                f"{p}: schema version {f.attrs['schema_version']} is newer than this FreiPose "
                f"reads ({SCHEMA_VERSION}); upgrade FreiPose"
            )
        need = ["frame_index", "cameras", "boxes", "scores", "agree", "n_agree", "center"]
        need.append("crop_boxes")
        missing = [k for k in need if k not in f]
        if missing:
            raise BoxesFormatError(f"{p}: missing datasets {missing}")
        arrays = {k: f[k][()] for k in need}
        cams = decode_strings(arrays.pop("cameras"))
        rig = None
        if "calibration" in f.attrs:
            rig = rig_from_toml_text(str(f.attrs["calibration"]), source=f"{p} (calibration)")
        reserved = {"schema", "schema_version", "units", "freipose_version", "method"}
        reserved |= {"cube_size", "calibration"}
        extra = {k: f.attrs[k] for k in f.attrs if k not in reserved}
        try:
            return BoxesData(
                cameras=tuple(cams),
                cube_size=float(f.attrs.get("cube_size", np.nan)),
                method=str(f.attrs.get("method", "")),
                calibration=rig,
                attrs=extra,
                **arrays,
            )
        except ValueError as exc:
            raise BoxesFormatError(f"{p}: {exc}") from exc
