"""The native calibration file ``calibration.toml`` (a superset of Anipose's).

One ``[cam_N]`` table per camera (name, size, matrix, distortions, rotation (a Rodrigues
vector, or a 3x3 matrix when read) and translation, world -> camera) and a ``[metadata]``
table; lengths are stored in mm.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from freipose.errors import FreiPoseError
from freipose.geometry.camera import Camera, CameraRig
from freipose.geometry.transforms import rodrigues_to_matrix
from freipose.io.atomic import atomic_write_text
from freipose.io.toml import check_keys, did_you_mean, parse_toml, read_toml

log = logging.getLogger(__name__)

UNIT_SCALE_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}


class CalibrationFormatError(FreiPoseError):
    """A calibration file is malformed; the message names the file and the problem."""


def _cam_index(key: str) -> int:
    m = re.fullmatch(r"cam_(\d+)", key)
    return int(m.group(1)) if m else -1


def rig_to_toml_dict(rig: CameraRig) -> dict[str, Any]:
    """The ``calibration.toml`` structure for a rig (numeric ``cam_N`` tables + metadata)."""
    out: dict[str, Any] = {}
    for i, cam in enumerate(rig):
        out[f"cam_{i}"] = {
            "name": cam.name,
            "size": [int(cam.size[0]), int(cam.size[1])],
            "matrix": cam.K.tolist(),
            "distortions": cam.dist.tolist(),
            "rotation": cam.rvec.tolist(),
            "translation": cam.t.tolist(),
        }
    md = {k: toml_value(v) for k, v in rig.metadata.items() if v is not None}
    md["units"] = "mm"
    out["metadata"] = md
    return out


def toml_value(v: Any) -> Any:
    """``v`` as a TOML value: arrays and NumPy scalars as Python values, paths as strings.

    ``None`` entries of dicts are left out (TOML has no null).
    """
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, (np.bool_, Path)):
        return v.item() if isinstance(v, np.bool_) else str(v)
    if isinstance(v, dict):  # TOML has no null: None entries are left out
        return {str(k): toml_value(x) for k, x in v.items() if x is not None}
    if isinstance(v, (list, tuple)):
        return [toml_value(x) for x in v]
    return v


# The keys of a [cam_N] table; ``fisheye`` is Anipose's flag (only false is supported).
CAMERA_KEYS = ("name", "size", "matrix", "distortions", "rotation", "translation", "fisheye")


def _check_tables(data: dict[str, Any], cams: list[str], source: str) -> None:
    """Reject top-level entries other than ``[cam_N]`` tables and ``[metadata]``."""
    known = [*cams, "metadata"]
    for k in data:
        if k not in known:
            hint = did_you_mean(k, [*known, f"cam_{len(cams)}"])
            raise CalibrationFormatError(
                f"{source}: unknown table {k!r}{hint}; a calibration file holds one [cam_N] "
                f"table per camera (cam_0, cam_1, ...) and an optional [metadata] table"
            )


def _check_camera_keys(tab: Any, key: str, source: str) -> None:
    """Reject unknown keys of a ``[cam_N]`` table (with a did-you-mean) and fisheye cameras."""
    if not isinstance(tab, dict):
        raise CalibrationFormatError(f"{source}: [{key}] must be a table, got {tab!r}")
    check_keys(tab, CAMERA_KEYS, f"{source}: [{key}]", CalibrationFormatError)
    if tab.get("fisheye", False):
        raise CalibrationFormatError(
            f"{source}: [{key}] is a fisheye camera (fisheye = true); FreiPose supports the "
            f"pinhole model with OpenCV's 5 distortion coefficients only"
        )


def as_rotation(R: Any, source: str, name: str) -> np.ndarray:
    """A 3x3 rotation matrix, checked; tiny non-orthonormality (few stored digits) is removed.

    Args:
        R: the matrix (9 values).
        source: the file, for messages.
        name: the camera, for messages.

    Returns:
        The rotation (3, 3): ``R`` itself, or the nearest rotation when ``R R^T`` is within
        1e-3 of the identity.

    Raises:
        CalibrationFormatError: not 9 finite values, or not a rotation (``R R^T`` further
            from the identity, or a determinant that is not +1: a reflection).
    """
    R = np.asarray(R, dtype=np.float64)
    if R.size != 9:
        raise CalibrationFormatError(
            f"{source}: camera {name!r}: rotation must be 3x3, got {R.shape}"
        )
    R = R.reshape(3, 3)
    if not np.all(np.isfinite(R)):
        raise CalibrationFormatError(f"{source}: camera {name!r}: rotation has NaN/inf values")
    err, det = float(np.abs(R @ R.T - np.eye(3)).max()), float(np.linalg.det(R))
    if err >= 1e-3 or det <= 0:
        raise CalibrationFormatError(
            f"{source}: camera {name!r}: the 3x3 rotation is not a rotation matrix (R R^T "
            f"differs from the identity by {err:.3g}, determinant {det:.3g}; a rotation has "
            "orthonormal rows and determinant +1): check the file's rotation of this camera"
        )
    if err > 1e-6:
        u, _, vt = np.linalg.svd(R)
        log.warning(
            "%s: camera %r: rotation is orthonormal only to %.1e; using the nearest rotation",
            source,
            name,
            err,
        )
        R = u @ vt
    return R


def _rotation(value: Any, key: str, name: str, source: str) -> np.ndarray:
    """The world->camera rotation of table ``key``: a Rodrigues vector or a 3x3 matrix.

    Raises:
        CalibrationFormatError: another shape, or a 3x3 matrix that is not a rotation.
    """
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        arr = None
    if arr is not None and arr.shape in ((3,), (3, 1), (1, 3)):
        return rodrigues_to_matrix(arr)
    if arr is not None and arr.shape == (3, 3):
        return as_rotation(arr, source, name)
    raise CalibrationFormatError(
        f"{source}: [{key}] (camera {name!r}): rotation must be a Rodrigues vector of 3 "
        f"values or a 3x3 rotation matrix (world->camera), got "
        + (f"shape {arr.shape}" if arr is not None else repr(value))
    )


def rig_from_toml_dict(
    data: dict[str, Any], source: str = "<toml>", units: str | None = None
) -> CameraRig:
    """Parse the ``calibration.toml`` structure; lengths are converted to millimetres.

    Args:
        data: the parsed TOML.
        source: file name for error messages.
        units: units of the stored translations when ``metadata.units`` is absent
            (Anipose files often omit it); default ``mm``.
    """
    keys = sorted((k for k in data if _cam_index(k) >= 0), key=_cam_index)
    _check_tables(data, keys, source)
    if not keys:
        raise CalibrationFormatError(
            f"{source}: no [cam_N] tables found; expected one table per camera such as "
            f"[cam_0] with name, size, matrix, distortions, rotation, translation"
        )
    md = dict(data.get("metadata", {}))
    unit = str(md.get("units", units or "mm"))
    if unit not in UNIT_SCALE_TO_MM:
        raise CalibrationFormatError(
            f"{source}: metadata.units is {unit!r}; expected one of {sorted(UNIT_SCALE_TO_MM)}"
        )
    scale = UNIT_SCALE_TO_MM[unit]
    cams = []
    for k in keys:
        tab = data[k]
        _check_camera_keys(tab, k, source)
        missing = [f for f in ("size", "matrix", "rotation", "translation") if f not in tab]
        if missing:
            raise CalibrationFormatError(
                f"{source}: [{k}] lacks {missing}; every camera needs size, matrix, "
                "distortions, rotation (world->camera: Rodrigues vector or 3x3 matrix) and "
                "translation"
            )
        try:
            name = str(tab.get("name", k))
            cams.append(
                Camera(
                    name,
                    tuple(tab["size"]),
                    tab["matrix"],
                    tab.get("distortions", [0.0] * 5),
                    _rotation(tab["rotation"], k, name, source),
                    np.asarray(tab["translation"], dtype=np.float64) * scale,
                )
            )
        except ValueError as exc:
            raise CalibrationFormatError(f"{source}: [{k}]: {exc}") from exc
    md["units"] = "mm"
    return CameraRig(tuple(cams), md)


def read_calibration_toml(path: str | Path, units: str | None = None) -> CameraRig:
    """Read a native or Anipose ``calibration.toml``.

    Args:
        path: the file.
        units: units of the stored translations when ``metadata.units`` is absent.

    Returns:
        The rig, lengths in mm.

    Raises:
        InputFileError: no such file.
        CalibrationFormatError: not TOML or not a calibration.
    """
    data = read_toml(path, "calibration file", CalibrationFormatError, "not a valid TOML file")
    return rig_from_toml_dict(data, str(path), units=units)


def write_calibration_toml(rig: CameraRig, path: str | Path) -> None:
    """Write the native ``calibration.toml`` atomically."""
    atomic_write_text(path, rig_to_toml_text(rig))


def rig_to_toml_text(rig: CameraRig) -> str:
    """The ``calibration.toml`` text for a rig (also embedded in HDF5 files)."""
    return tomli_w.dumps(rig_to_toml_dict(rig))


def rig_from_toml_text(text: str, source: str = "<embedded calibration>") -> CameraRig:
    """Parse ``calibration.toml`` text (as embedded in HDF5 files).

    Args:
        text: the TOML text.
        source: where the text comes from, for messages.

    Returns:
        The rig, lengths in mm.

    Raises:
        CalibrationFormatError: not TOML or not a calibration.
    """
    data = parse_toml(text, source, "calibration", CalibrationFormatError)
    return rig_from_toml_dict(data, source)
