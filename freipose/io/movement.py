"""movement's poses datasets (netCDF, ``.nc``): FreiPose poses as an xarray ``Dataset``.

The file is what ``movement`` (``pip install 'freipose[movement]'``) saves with
``ds.to_netcdf``: ``position`` float32 (time, space, keypoints, individuals) with
``space = x, y, z`` in world mm and one individual per animal, ``confidence`` float32 (time,
keypoints, individuals), coordinates ``time`` (seconds, ``frame_index / fps``),
``space``, ``keypoints``, ``individuals``, and the attributes ``ds_type = "poses"``,
``source_software = "FreiPose"``, ``fps``, ``time_unit = "seconds"``. FreiPose adds the
data variable ``frame_index`` (time) int64 and the attributes ``units = "mm"``, ``up``
(3,) and, where known, ``calibration``, ``skeleton`` (TOML text) and ``provenance`` (JSON),
and for several animals ``identity_confidence`` float32 (time, individuals) and the
attribute ``animal_axis = 1`` (the poses had an animal axis), so that a file it wrote reads
back exactly. A file of another tool without them gets
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
        poses: (T, K, 3) float32 mm, NaN where missing; (T, A, K, 3) with ``individuals``.
        confidence: (T, K) float32; (T, A, K) with ``individuals``.
        keypoints: (K,) names.
        frame_index: (T,) int64.
        fps: frames per second.
        attrs: the FreiPose attributes found (``up``, ``calibration``, ``skeleton``,
            ``provenance``).
        individuals: (A,) names of an animal axis, or None (one animal, no axis).
        identity_confidence: (T, A) float32, or None.
    """

    poses: np.ndarray
    confidence: np.ndarray
    keypoints: tuple[str, ...]
    frame_index: np.ndarray
    fps: float
    attrs: dict[str, Any]
    individuals: tuple[str, ...] | None = None
    identity_confidence: np.ndarray | None = None


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
        individual: the name of the one individual (poses without an animal axis).

    Raises:
        MovementFormatError: xarray or a netCDF engine is not installed.
    """
    xr = _xarray()
    multi = data.individuals is not None
    poses = data.poses if multi else data.poses[:, None]  # (T, A, K, 3)
    conf = data.confidence if multi else data.confidence[:, None]  # (T, A, K)
    names = list(data.individuals) if data.individuals is not None else [individual]
    position = np.transpose(poses.astype(np.float32), (0, 3, 2, 1))
    data_vars: dict[str, Any] = {
        "position": (("time", "space", "keypoints", "individuals"), position),
        "confidence": (
            ("time", "keypoints", "individuals"),
            np.transpose(conf.astype(np.float32), (0, 2, 1)),
        ),
        "frame_index": (("time",), data.frame_index.astype(np.int64)),
    }
    extra_attrs: dict[str, Any] = {"animal_axis": 1} if multi else {}
    if data.identity_confidence is not None:
        data_vars["identity_confidence"] = (
            ("time", "individuals"),
            np.asarray(data.identity_confidence, np.float32),
        )
    ds = xr.Dataset(
        data_vars=data_vars,
        coords={
            "time": data.frame_index / float(data.fps),
            "space": ["x", "y", "z"],
            "keypoints": list(data.keypoints),
            "individuals": names,
        },
        attrs={
            "source_software": "FreiPose",
            "ds_type": "poses",
            "fps": float(data.fps),
            "time_unit": "seconds",
            "units": "mm",
            **extra_attrs,
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
    """Read a movement poses dataset.

    One individual gives poses without an animal axis (unless FreiPose wrote the file with
    one, ``animal_axis = 1``); several give (T, A, K, 3) with their names.

    Raises:
        MovementFormatError: xarray is missing, or the file is not a movement poses dataset
            with x, y, z in mm.
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
    if pos.sizes["space"] != 3:
        raise MovementFormatError(
            f"{path}: FreiPose reads poses in 3D, found {pos.sizes['space']} space axes "
            f"({list(map(str, ds['space'].values))}); 2D poses are not 3D poses"
        )
    units = str(ds.attrs.get("units", "mm"))
    if units != "mm":
        raise MovementFormatError(f"{path}: units are {units!r}; FreiPose poses are in 'mm'")
    fps = float(ds.attrs.get("fps", np.nan))
    if not np.isfinite(fps) or fps <= 0:
        raise MovementFormatError(
            f"{path}: no fps attribute; load it with movement's fps= and save it again"
        )
    names = tuple(str(n) for n in ds["individuals"].values)
    multi = len(names) > 1 or int(ds.attrs.get("animal_axis", 0)) == 1
    poses = np.transpose(pos.transpose("time", "space", "keypoints", "individuals").values,
                         (0, 3, 2, 1))  # (T, A, K, 3)  # fmt: skip
    if "confidence" in ds:
        conf = np.transpose(
            ds["confidence"].transpose("time", "keypoints", "individuals").values, (0, 2, 1)
        )
    else:
        conf = np.isfinite(poses).all(axis=-1).astype(np.float32)
    ident = None
    if multi and "identity_confidence" in ds:
        ident = ds["identity_confidence"].transpose("time", "individuals").values
        ident = ident.astype(np.float32)
    if not multi:
        poses, conf = poses[:, 0], conf[:, 0]
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
        individuals=names if multi else None,
        identity_confidence=ident,
    )
