"""movement's poses datasets (netCDF, ``.nc``): FreiPose poses as an xarray ``Dataset``.

The file is what ``movement`` (``pip install 'freipose[movement]'``) saves with
``ds.to_netcdf``: ``position`` float32 (time, space, keypoints, individuals) with
``space = x, y, z`` in world mm and one individual, ``confidence`` float32 (time,
keypoints, individuals), coordinates ``time`` (seconds, ``frame_index / fps``),
``space``, ``keypoints``, ``individuals``, and the attributes ``ds_type = "poses"``,
``source_software = "FreiPose"``, ``fps``, ``time_unit = "seconds"``. FreiPose adds the
data variable ``frame_index`` (time) int64 and the attributes ``units = "mm"``, ``up``
(3,) and, where known, ``calibration``, ``skeleton`` (TOML text) and ``provenance`` (JSON),
so that a file it wrote reads back exactly. A file of another tool without them gets
``frame_index = round(time * fps)`` (or ``time`` itself when ``time_unit`` is frames) and
up ``+z``.

This module works on plain arrays and strings; ``freipose.io.poses`` turns them into
``PoseData``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from freipose.errors import FreiPoseError
from freipose.io.atomic import atomic_path

SUFFIX = ".nc"
INSTALL = "pip install 'freipose[movement]'"


class MovementFormatError(FreiPoseError):
    """A movement file cannot be read or written (the message says why and the fix)."""


@dataclass(frozen=True)
class MovementPoses:
    """The contents of a movement poses file, as plain arrays.

    Attributes:
        poses: (T, K, 3) float32 mm, NaN where missing.
        confidence: (T, K) float32.
        keypoints: (K,) names.
        frame_index: (T,) int64.
        fps: frames per second.
        attrs: the FreiPose attributes found (``up``, ``calibration``, ``skeleton``,
            ``provenance``).
    """

    poses: np.ndarray
    confidence: np.ndarray
    keypoints: tuple[str, ...]
    frame_index: np.ndarray
    fps: float
    attrs: dict[str, Any]


def _xarray() -> Any:
    try:
        import xarray
    except ImportError as exc:
        raise MovementFormatError(
            f"movement files (.nc) need xarray and a netCDF engine: {INSTALL}"
        ) from exc
    return xarray


def write_movement(path: str | Path, data: MovementPoses, individual: str = "individual_0") -> Path:
    """Write a movement poses dataset to ``path`` (netCDF, atomically).

    Args:
        path: the output ``.nc`` file.
        data: the poses; ``attrs`` values must be strings or numeric arrays.
        individual: the name of the one individual.

    Raises:
        MovementFormatError: xarray or a netCDF engine is not installed.
    """
    xr = _xarray()
    position = np.transpose(data.poses.astype(np.float32), (0, 2, 1))[..., None]
    ds = xr.Dataset(
        data_vars={
            "position": (("time", "space", "keypoints", "individuals"), position),
            "confidence": (
                ("time", "keypoints", "individuals"),
                data.confidence.astype(np.float32)[..., None],
            ),
            "frame_index": (("time",), data.frame_index.astype(np.int64)),
        },
        coords={
            "time": data.frame_index / float(data.fps),
            "space": ["x", "y", "z"],
            "keypoints": list(data.keypoints),
            "individuals": [individual],
        },
        attrs={
            "source_software": "FreiPose",
            "ds_type": "poses",
            "fps": float(data.fps),
            "time_unit": "seconds",
            "units": "mm",
            **data.attrs,
        },
    )
    with atomic_path(path) as tmp:
        try:
            ds.to_netcdf(tmp)
        except ValueError as exc:  # no netCDF engine installed
            raise MovementFormatError(f"cannot write {path}: {exc}; {INSTALL}") from exc
    return Path(path)


def read_movement(path: str | Path) -> MovementPoses:
    """Read a movement poses dataset (one individual).

    Raises:
        MovementFormatError: xarray is missing, or the file is not a movement poses dataset
            of one individual with x, y, z in mm.
    """
    xr = _xarray()
    try:
        ds = xr.open_dataset(path).load()
    except (OSError, ValueError) as exc:
        raise MovementFormatError(
            f"{path}: not a readable netCDF file ({exc}); expected a movement poses dataset"
        ) from exc
    with ds:
        return _from_dataset(ds, Path(path))


def _from_dataset(ds: Any, path: Path) -> MovementPoses:
    """The arrays of an open movement dataset."""
    if "position" not in ds or ds["position"].dims != ("time", "space", "keypoints", "individuals"):
        raise MovementFormatError(
            f"{path}: expected a movement poses dataset with position (time, space, keypoints, "
            f"individuals), found variables {sorted(ds.data_vars)}"
        )
    pos = ds["position"]
    if pos.sizes["individuals"] != 1 or pos.sizes["space"] != 3:
        raise MovementFormatError(
            f"{path}: FreiPose reads one individual in 3D, found {pos.sizes['individuals']} "
            f"individuals and {pos.sizes['space']} space axes; select one with "
            "ds.sel(individuals=[NAME]) and save that"
        )
    units = str(ds.attrs.get("units", "mm"))
    if units != "mm":
        raise MovementFormatError(f"{path}: units are {units!r}; FreiPose poses are in 'mm'")
    fps = float(ds.attrs.get("fps", np.nan))
    if not np.isfinite(fps) or fps <= 0:
        raise MovementFormatError(
            f"{path}: no fps attribute; load it with movement's fps= and save it again"
        )
    poses = np.transpose(pos.transpose("time", "space", "keypoints", "individuals").values[..., 0],
                         (0, 2, 1))  # fmt: skip
    if "confidence" in ds:
        conf = ds["confidence"].transpose("time", "keypoints", "individuals").values[..., 0]
    else:
        conf = np.isfinite(poses).all(axis=-1).astype(np.float32)
    if "frame_index" in ds:
        frames = ds["frame_index"].values.astype(np.int64)
    else:
        t = np.asarray(ds["time"].values, np.float64)
        seconds = ds.attrs.get("time_unit", "seconds") == "seconds"
        frames = np.round(t * fps if seconds else t).astype(np.int64)
    attrs = {k: ds.attrs[k] for k in ("up", "calibration", "skeleton", "provenance")
             if k in ds.attrs}  # fmt: skip
    return MovementPoses(
        poses=poses.astype(np.float32),
        confidence=np.nan_to_num(conf.astype(np.float32), nan=0.0),
        keypoints=tuple(str(k) for k in ds["keypoints"].values),
        frame_index=frames,
        fps=fps,
        attrs=attrs,
    )
