"""Calibration files in any supported format: the format by suffix or by name, and dispatch.

``load_calibration(path)`` / ``save_calibration(rig, path)`` pick the format by suffix or by
an explicit ``fmt``. The native ``calibration.toml`` is :mod:`freipose.io.calibration_toml`;
other tools' formats are :mod:`freipose.io.calibration_formats`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from types import MappingProxyType

from freipose.errors import InputFileError
from freipose.geometry.camera import CameraRig
from freipose.io import calibration_formats as formats
from freipose.io.calibration_toml import (
    CalibrationFormatError,
    read_calibration_toml,
    write_calibration_toml,
)

Reader = Callable[[Path], CameraRig]
Writer = Callable[[CameraRig, Path], None]

# Format name -> reader / writer.
READERS: Mapping[str, Reader] = MappingProxyType({"toml": read_calibration_toml, **formats.READERS})
WRITERS: Mapping[str, Writer] = MappingProxyType(
    {"toml": write_calibration_toml, **formats.WRITERS}
)
# Suffix (lower case) -> format name; the key "/" names the format of an existing folder.
SUFFIXES: Mapping[str, str] = MappingProxyType({".toml": "toml", **formats.SUFFIXES})


def detect_format(path: str | Path, fmt: str | None = None) -> str:
    """The calibration format of ``path``: ``fmt`` if given, else from the suffix."""
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
        raise InputFileError(f"calibration file not found: {path}")
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
