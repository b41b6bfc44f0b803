"""Board files: TOML or JSON board descriptions (and FreiCalib marker JSON), read and written."""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from dataclasses import MISSING, fields
from pathlib import Path
from types import MappingProxyType
from typing import Any

from freipose.calibration.boards import (
    AprilGridBoard,
    Board,
    BoardError,
    CharucoBoard,
    ChessboardBoard,
    require_positive,
)
from freipose.errors import InputFileError
from freipose.io.toml import check_keys, parse_toml

logger = logging.getLogger(__name__)

__all__ = ["board_from_dict", "load_board", "save_board"]

_TYPES: Mapping[str, type] = MappingProxyType(
    {
        "charuco": CharucoBoard,
        "chessboard": ChessboardBoard,
        "checkerboard": ChessboardBoard,
        "aprilgrid": AprilGridBoard,
    }
)


def _from_freicalib_marker(d: Mapping[str, Any], source: str) -> AprilGridBoard:
    """FreiCalib marker JSON ``{family, border, double, tsize, tspace, n_x, n_y, offset}``.

    ``tsize`` is in metres; ``tspace`` is the gap in metres (a value >= ``tsize`` is read as a
    fraction of the tag size instead, as ``create_marker.py --tspace`` takes it).
    """
    missing = [k for k in ("tsize", "tspace", "n_x", "n_y") if k not in d]
    if missing:
        raise BoardError(f"{source}: FreiCalib marker file lacks {', '.join(missing)}")
    tsize = require_positive("tsize", d["tsize"])
    tspace = require_positive("tspace", d["tspace"])
    frac = tspace / tsize if tspace < tsize else tspace
    if d.get("double"):
        logger.warning("%s: double-sided FreiCalib board; only the front side is used", source)
    fam = str(d.get("family", "36h11"))
    return AprilGridBoard(
        tags_x=d["n_x"],
        tags_y=d["n_y"],
        tag_size=tsize * 1000.0,
        tag_spacing=frac,
        family=fam,
        border=d.get("border", 2),
    )


def board_from_dict(d: Mapping[str, Any], source: str = "<dict>") -> Board:
    """Build a board from a mapping with ``type`` = ``charuco`` | ``chessboard`` | ``aprilgrid``.

    A FreiCalib marker JSON (``tsize``/``tspace``/``n_x``/``n_y``, no ``type``) is also accepted.
    A ``[board]`` table is unwrapped.

    Args:
        d: the board's fields.
        source: where they come from (a file name), for messages.

    Returns:
        the board.

    Raises:
        BoardError: a missing, unknown (with a "did you mean") or invalid field.
    """
    if not isinstance(d, Mapping):
        raise BoardError(f"{source}: expected a table of board fields, got {type(d).__name__}")
    if "type" not in d and isinstance(d.get("board"), Mapping):
        d = d["board"]
    if "type" not in d:
        if "tsize" in d and "n_x" in d:
            return _from_freicalib_marker(d, source)
        raise BoardError(
            f'{source}: missing field \'type\'; expected type = "charuco", "chessboard" or '
            f'"aprilgrid"'
        )
    kind = str(d["type"]).strip().lower()
    if kind not in _TYPES:
        raise BoardError(
            f"{source}: unknown board type {d['type']!r}; expected charuco, chessboard or aprilgrid"
        )
    cls = _TYPES[kind]
    names = [f.name for f in fields(cls)]
    required = [f.name for f in fields(cls) if f.default is MISSING]
    missing = [n for n in required if n not in d]
    if missing:
        raise BoardError(
            f"{source}: {kind} board lacks required field(s) {', '.join(missing)} "
            f"(a {kind} board needs {', '.join(required)})"
        )
    check_keys(d, [*names, "type"], f"{source}: {kind} board", BoardError)
    try:
        return cls(**{k: d[k] for k in names if k in d})
    except BoardError as exc:
        raise BoardError(f"{source}: {exc}") from None


def load_board(path: str | Path) -> Board:
    """Read a board from TOML or JSON (including FreiCalib marker JSON).

    A ``.json`` file is JSON, a ``.toml`` file TOML; a file with another suffix is read as
    TOML, else as JSON.

    Args:
        path: the board file.

    Returns:
        the board.

    Raises:
        InputFileError: no such file.
        BoardError: the file is not valid TOML or JSON, or describes no valid board.
    """
    p = Path(path)
    if not p.is_file():
        raise InputFileError(f"board file {p} does not exist")
    text = p.read_text(encoding="utf-8")
    suffix = p.suffix.lower()
    if suffix == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise BoardError(f"{p}: not valid JSON ({exc})") from None
        return board_from_dict(data, source=str(p))
    invalid = "not valid TOML" if suffix == ".toml" else "neither valid TOML nor JSON"
    try:
        data = parse_toml(text, str(p), "board file", BoardError, invalid)
    except BoardError as toml_error:
        if suffix == ".toml":
            raise
        try:
            data = json.loads(text)
        except json.JSONDecodeError:
            raise toml_error from None
    return board_from_dict(data, source=str(p))


def save_board(board: Board, path: str | Path) -> None:
    """Write a board as TOML (or JSON for a ``.json`` suffix), atomically.

    Args:
        board: the board.
        path: the file to write.
    """
    from freipose.io.atomic import atomic_write_text

    p = Path(path)
    d = board.to_dict()
    if p.suffix.lower() == ".json":
        atomic_write_text(p, json.dumps(d, indent=2) + "\n")
    else:
        import tomli_w

        atomic_write_text(p, tomli_w.dumps(d))
