"""HDF5 helpers shared by the FreiPose file formats (poses.h5, labels.h5, boxes.h5)."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import h5py
import numpy as np

from freipose.errors import InputFileError


def str_array(values: Iterable[object]) -> np.ndarray:
    """(N,) UTF-8 variable-length strings for an HDF5 dataset."""
    return np.array([str(v) for v in values], dtype=h5py.string_dtype("utf-8"))


def decode_strings(arr: Iterable[object]) -> list[str]:
    """Strings read back from an HDF5 dataset (bytes decoded as UTF-8)."""
    return [s.decode() if isinstance(s, bytes) else str(s) for s in arr]


def open_h5(path: str | Path, what: str, error: type[Exception]) -> h5py.File:
    """Open an existing HDF5 file for reading (use it as a context manager).

    Args:
        path: the file.
        what: what the file is, for the message (e.g. ``"labels file"``).
        error: the exception class raised when the file is not readable HDF5.

    Raises:
        InputFileError: the file does not exist (a ``FileNotFoundError`` too).
        error: the file exists but is not readable HDF5 (e.g. truncated).
    """
    path = Path(path)
    if not path.exists():
        raise InputFileError(f"{what} not found: {path}")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise error(f"{path}: not a readable HDF5 file ({exc}); is it truncated?") from exc
