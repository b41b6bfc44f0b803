"""Reading MATLAB ``.mat`` files (v5 through scipy, v7.3 through h5py) into plain Python.

:func:`load_mat` returns the same structure for both versions:

* a struct (1x1) becomes a ``dict`` of its fields; a struct array becomes a ``list`` of
  dicts in MATLAB (column-major) order;
* a cell array becomes a ``list`` of its converted elements in column-major order;
* a char array becomes a ``str`` (a multi-row char matrix a ``list`` of ``str``);
* numeric and logical arrays become NumPy arrays with MATLAB's shape (at least 2-D,
  e.g. a row vector is ``(1, n)``), never squeezed, so ``(1, 44)`` stays ``(1, 44)``.

MATLAB stores arrays column-major; v7.3 (HDF5) datasets therefore appear transposed in
h5py and are transposed back here.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from freipose.errors import FreiPoseError, InputFileError

log = logging.getLogger(__name__)

_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"


class MatFileError(FreiPoseError):
    """A ``.mat`` file cannot be read; the message names the file and the reason."""


def load_mat(path: str | Path) -> dict[str, Any]:
    """Load the variables of a MATLAB ``.mat`` file (v5, v6, v7 or v7.3).

    Args:
        path: the ``.mat`` file.

    Returns:
        ``{variable name: value}`` converted as described in the module docstring.

    Raises:
        FileNotFoundError: the file does not exist.
        MatFileError: the file is not a readable MATLAB file.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"MATLAB file not found: {path}")
    if _is_hdf5(path):
        return _load_v73(path)
    import scipy.io

    try:
        raw = scipy.io.loadmat(
            str(path), struct_as_record=True, squeeze_me=False, chars_as_strings=True
        )
    except (ValueError, TypeError, OSError, NotImplementedError) as exc:
        raise MatFileError(
            f"{path}: not a readable MATLAB .mat file ({exc}); expected a MATLAB v5/v7 or "
            f"v7.3 file as saved by MATLAB's save()"
        ) from exc
    return {k: _from_scipy(v) for k, v in raw.items() if not k.startswith("__")}


def _is_hdf5(path: Path) -> bool:
    """v7.3 files are HDF5 with a 512-byte user block; plain HDF5 starts with the magic."""
    with open(path, "rb") as fh:
        head = fh.read(520)
    return head[:8] == _HDF5_MAGIC or head[512:520] == _HDF5_MAGIC


# -- v5 (scipy) -----------------------------------------------------------------------
def _from_scipy(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        if v.dtype.names is not None:  # struct (array)
            items = [
                {name: _from_scipy(rec[name]) for name in v.dtype.names}
                for rec in v.ravel(order="F")
            ]
            return items[0] if v.size == 1 else items
        if v.dtype == object:  # cell array
            return [_from_scipy(x) for x in v.ravel(order="F")]
        if v.dtype.kind == "U":  # char array
            strs = [str(s) for s in v.ravel(order="F")]
            return strs[0] if len(strs) == 1 else (strs if strs else "")
        if v.ndim < 2:
            return np.atleast_2d(v)
        return v
    if isinstance(v, str):
        return v
    return v


# -- v7.3 (h5py) ----------------------------------------------------------------------
def _load_v73(path: Path) -> dict[str, Any]:
    import h5py

    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise MatFileError(f"{path}: not a readable MATLAB v7.3 (HDF5) file ({exc})") from exc
    with f:
        out = {}
        for name, obj in f.items():
            if name.startswith("#"):  # '#refs#' and '#subsystem#' hold referenced data
                continue
            try:
                out[name] = _from_h5(obj, f)
            except (KeyError, ValueError, OSError) as exc:
                raise MatFileError(f"{path}: variable {name!r} cannot be read ({exc})") from exc
        return out


def _matlab_class(obj: Any) -> str:
    c = obj.attrs.get("MATLAB_class", b"")
    return c.decode() if isinstance(c, bytes) else str(c)


def _from_h5(obj: Any, f: Any) -> Any:
    import h5py

    cls = _matlab_class(obj)
    if isinstance(obj, h5py.Group):
        names = _field_names(obj)
        members = [obj[n] for n in names]
        if members and all(
            isinstance(m, h5py.Dataset) and m.dtype == h5py.ref_dtype and not _matlab_class(m)
            for m in members
        ):
            # A struct array: each field is an array of references, one per element.
            cols = {n: np.asarray(m[()]).T.ravel(order="F") for n, m in zip(names, members)}
            count = len(next(iter(cols.values())))
            items = [{n: _from_h5(f[cols[n][i]], f) for n in names} for i in range(count)]
            return items[0] if count == 1 else items
        # A 1x1 struct: one member per field (MATLAB_fields lists them in order).
        return {n: _from_h5(m, f) for n, m in zip(names, members)}
    # A dataset.
    if int(obj.attrs.get("MATLAB_empty", 0)):
        if cls == "char":
            return ""
        if cls == "cell":
            return []
        return np.zeros((0, 0))
    data = obj[()]
    if cls == "cell" or data.dtype == h5py.ref_dtype:
        refs = np.asarray(data).T  # back to MATLAB's shape
        return [_from_h5(f[r], f) for r in refs.ravel(order="F")]
    if cls == "struct":
        # A struct array: a dataset of references per field is stored in a group, handled
        # above; a dataset with MATLAB_class struct is an empty struct.
        return {}
    arr = np.asarray(data).T
    if cls == "char":
        a2 = np.atleast_2d(arr)
        rows = ["".join(chr(int(c)) for c in row) for row in a2]
        return rows[0] if len(rows) == 1 else rows
    if cls == "logical":
        arr = arr.astype(bool)
    if arr.dtype.names is not None and {"real", "imag"} <= set(arr.dtype.names):
        arr = arr["real"] + 1j * arr["imag"]
    return np.atleast_2d(arr)


def _field_names(group: Any) -> list[str]:
    raw = group.attrs.get("MATLAB_fields")
    if raw is None:
        return list(group.keys())
    names = []
    for entry in raw:
        chars = np.asarray(entry).ravel()
        names.append("".join(c.decode() if isinstance(c, bytes) else str(c) for c in chars))
    return [n for n in names if n in group] or list(group.keys())
