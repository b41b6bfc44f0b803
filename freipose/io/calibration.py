"""Calibration files: the native ``calibration.toml`` (a superset of Anipose's) and dispatch.

``load_calibration(path)`` / ``save_calibration(rig, path)`` pick the format by suffix or by
an explicit ``fmt``; the readers and writers for other tools' formats register in
``READERS`` / ``WRITERS``.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from freipose._compat import tomllib
from freipose.geometry.camera import Camera, CameraRig
from freipose.io.atomic import atomic_write_text

log = logging.getLogger(__name__)

UNIT_SCALE_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}


class CalibrationFormatError(ValueError):
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
    md = {k: _toml_value(v) for k, v in rig.metadata.items() if v is not None}
    md["units"] = "mm"
    out["metadata"] = md
    return out


def _toml_value(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, (np.bool_, Path)):
        return v.item() if isinstance(v, np.bool_) else str(v)
    if isinstance(v, dict):  # TOML has no null: None entries are left out
        return {str(k): _toml_value(x) for k, x in v.items() if x is not None}
    if isinstance(v, (list, tuple)):
        return [_toml_value(x) for x in v]
    return v


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
        missing = [f for f in ("size", "matrix", "rotation", "translation") if f not in tab]
        if missing:
            raise CalibrationFormatError(
                f"{source}: [{k}] lacks {missing}; every camera needs size, matrix, "
                f"distortions, rotation (Rodrigues, world->camera) and translation"
            )
        try:
            cams.append(
                Camera.from_rvec(
                    str(tab.get("name", k)),
                    tuple(tab["size"]),
                    tab["matrix"],
                    tab.get("distortions", [0.0] * 5),
                    tab["rotation"],
                    np.asarray(tab["translation"], dtype=np.float64) * scale,
                )
            )
        except ValueError as exc:
            raise CalibrationFormatError(f"{source}: [{k}]: {exc}") from exc
    md["units"] = "mm"
    return CameraRig(tuple(cams), md)


def read_calibration_toml(path: str | Path, units: str | None = None) -> CameraRig:
    """Read a native or Anipose ``calibration.toml``."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise CalibrationFormatError(f"{path}: not a valid TOML file ({exc})") from exc
    return rig_from_toml_dict(data, str(path), units=units)


def write_calibration_toml(rig: CameraRig, path: str | Path) -> None:
    """Write the native ``calibration.toml`` atomically."""
    atomic_write_text(path, rig_to_toml_text(rig))


def rig_to_toml_text(rig: CameraRig) -> str:
    """The ``calibration.toml`` text for a rig (also embedded in HDF5 files)."""
    return tomli_w.dumps(rig_to_toml_dict(rig))


def rig_from_toml_text(text: str, source: str = "<embedded calibration>") -> CameraRig:
    """Parse ``calibration.toml`` text (as embedded in HDF5 files)."""
    try:
        return rig_from_toml_dict(tomllib.loads(text), source)
    except tomllib.TOMLDecodeError as exc:
        raise CalibrationFormatError(f"{source}: not valid TOML ({exc})") from exc


Reader = Callable[[Path], CameraRig]
Writer = Callable[[CameraRig, Path], None]

# Format name -> reader / writer. Other modules register more formats here.
READERS: dict[str, Reader] = {"toml": read_calibration_toml}
WRITERS: dict[str, Writer] = {"toml": write_calibration_toml}
# Suffix (lower case) -> format name; the key "/" names the format of an existing folder.
SUFFIXES: dict[str, str] = {".toml": "toml"}


def _register_builtin_formats() -> None:
    """Import the modules that add other tools' formats to the tables above."""
    try:
        import freipose.io.calibration_formats  # noqa: F401
    except ImportError as exc:  # pragma: no cover - only while a format module is missing
        if "calibration_formats" not in str(exc):
            raise


def detect_format(path: str | Path, fmt: str | None = None) -> str:
    """The calibration format of ``path``: ``fmt`` if given, else from the suffix."""
    _register_builtin_formats()
    if fmt is not None:
        if fmt not in READERS and fmt not in WRITERS:
            raise CalibrationFormatError(
                f"unknown calibration format {fmt!r}; known: {sorted(set(READERS) | set(WRITERS))}"
            )
        return fmt
    p = Path(path)
    if p.is_dir() and "/" in SUFFIXES:
        return SUFFIXES["/"]
    name = p.name.lower()
    for sfx, f in sorted(SUFFIXES.items(), key=lambda kv: -len(kv[0])):
        if sfx != "/" and name.endswith(sfx):
            return f
    raise CalibrationFormatError(
        f"cannot tell the calibration format of {p.name!r} from its suffix; known suffixes: "
        f"{sorted(s for s in SUFFIXES if s != '/')}; pass --format one of "
        f"{sorted(set(READERS) | set(WRITERS))}"
    )


def load_calibration(path: str | Path, fmt: str | None = None) -> CameraRig:
    """Read a calibration in any supported format (by suffix or ``fmt``); lengths in mm."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"calibration file not found: {path}")
    f = detect_format(path, fmt)
    if f not in READERS:
        raise CalibrationFormatError(f"format {f!r} can be written but not read")
    return READERS[f](path)


def save_calibration(rig: CameraRig, path: str | Path, fmt: str | None = None) -> None:
    """Write a calibration in any supported format (by suffix or ``fmt``), atomically."""
    f = detect_format(path, fmt)
    if f not in WRITERS:
        raise CalibrationFormatError(f"format {f!r} can be read but not written")
    WRITERS[f](rig, Path(path))
