"""Reading TOML files and tables with messages that name the file, the key and the fix.

Every TOML file FreiPose reads (configs, rigs, boards, studies, skeletons, mappings,
calibrations) is parsed by :func:`read_toml` or :func:`parse_toml`, and every table that
becomes a dataclass or a fixed set of keys is checked by :func:`check_keys` or built by
:func:`dataclass_from_table`, so that a typo is an error with a "did you mean" instead of
a key that is silently ignored.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, TypeVar

from freipose._compat import tomllib
from freipose.errors import FreiPoseError, InputFileError

T = TypeVar("T")

Bounds = tuple[float, float, str]
"""An allowed closed range of a number and what the number measures (its unit)."""


class TomlFileError(FreiPoseError):
    """A TOML file that cannot be parsed or holds an unknown key."""


def parse_toml(
    text: str,
    source: str,
    what: str = "file",
    error: type[Exception] = TomlFileError,
    invalid: str = "not valid TOML",
) -> dict[str, Any]:
    """Parse TOML ``text`` read from ``source`` (a path or a description, for messages).

    Args:
        text: the TOML text.
        source: where the text comes from (a path or a description), for messages.
        what: what the text is ("study file"), for messages.
        error: the exception class raised for text that is not TOML.
        invalid: the words of the message that say the text is not TOML.

    Returns:
        The parsed tables.

    Raises:
        error: the text is not valid TOML; the message names ``what``, ``source`` and the
            parser's line and column.
    """
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{what} {source}: {invalid} ({exc})") from None


def read_toml(
    path: str | Path,
    what: str = "file",
    error: type[Exception] = TomlFileError,
    invalid: str = "not valid TOML",
) -> dict[str, Any]:
    """Read and parse the TOML file ``path``; ``what`` names it in messages ("study file").

    Args:
        path: the TOML file.
        what: what the file is ("study file"), for messages.
        error: the exception class raised for a file that is not UTF-8 TOML.
        invalid: the words of the message that say the file is not TOML.

    Returns:
        The parsed tables.

    Raises:
        InputFileError: no such file (a ``FileNotFoundError`` too).
        error: not UTF-8 text or not valid TOML.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{what} not found: {path}")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{what} {path}: not a UTF-8 text file ({exc})") from None
    return parse_toml(text, str(path), what, error, invalid)


def did_you_mean(key: str, known: Iterable[str]) -> str:
    """``"; did you mean 'x'?"`` for the closest known key, or ``""`` when none is close."""
    close = difflib.get_close_matches(key, sorted(known), n=1)
    return f"; did you mean {close[0]!r}?" if close else ""


def check_keys(
    table: Mapping[str, Any],
    known: Iterable[str],
    where: str,
    error: type[Exception] = TomlFileError,
) -> None:
    """Raise ``error`` when ``table`` holds a key outside ``known``.

    The message names ``where`` (e.g. ``"train.toml [model]"``), the unknown key, the
    closest known key and all known keys.
    """
    known = sorted(known)
    unknown = [k for k in table if k not in known]
    if unknown:
        k = unknown[0]
        raise error(
            f"{where}: unknown key {k!r}{did_you_mean(k, known)} (known keys: {', '.join(known)})"
        )


def dataclass_from_table(
    cls: type[T],
    table: Mapping[str, Any],
    where: str,
    error: type[Exception] = TomlFileError,
    **fixed: Any,
) -> T:
    """Build the dataclass ``cls`` from ``table`` (plus ``fixed`` values), rejecting unknown keys.

    Values are passed as they are; ``cls.__post_init__`` checks them.
    """
    names = [f.name for f in dataclasses.fields(cls) if f.init]  # type: ignore[arg-type]
    check_keys(table, [n for n in names if n not in fixed], where, error)
    return cls(**dict(table), **fixed)


def check_number(
    value: Any, key: str, bounds: Bounds, error: type[Exception] = TomlFileError
) -> float:
    """``value`` as a float when it is a finite number within ``bounds``; else raise ``error``.

    Args:
        value: the value read from a table.
        key: its name in messages (``"schedule.lr"``).
        bounds: ``(low, high, meaning)``: the allowed closed range and what the value
            measures, for the message.
        error: the exception class raised.

    Returns:
        The value as a float.

    Raises:
        error: not a number, NaN, infinite or outside the range; the message names the
            key, the value and the allowed range.
    """
    low, high, meaning = bounds
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not number or not (math.isfinite(value) and low <= value <= high):
        raise error(
            f"{key} must be in [{low:g}, {high:g}] ({meaning}; a finite number), got {value!r}"
        )
    return float(value)


def check_numbers(
    obj: Any, table: str, ranges: Mapping[str, Bounds], error: type[Exception]
) -> None:
    """Check every field of the dataclass ``obj`` named in ``ranges`` with :func:`check_number`.

    A field holding a tuple or a list has each of its values checked.

    Args:
        obj: a dataclass instance (a config table).
        table: the table's name in messages (``"schedule"`` gives ``"schedule.lr"``).
        ranges: the bounds of the fields.
        error: the exception class raised.

    Raises:
        error: a value that is not a finite number within its field's bounds.
    """
    for name, bounds in ranges.items():
        value = getattr(obj, name)
        for v in value if isinstance(value, (tuple, list)) else (value,):
            check_number(v, f"{table}.{name}" if table else name, bounds, error)
