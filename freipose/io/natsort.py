"""Natural sort order: numbers inside names compare as numbers (``cam2`` before ``cam10``)."""

from __future__ import annotations

import re

_DIGITS = re.compile(r"(\d+)")


def natural_key(name: str) -> list[int | str]:
    """Sort key of ``name`` with embedded numbers compared numerically, letters case-blind.

    The key alternates text and number parts (``"Frame_10.png"`` -> ``["frame_", 10,
    ".png"]``), so keys of any two names compare without mixing types.

    Args:
        name: a file name, stem or camera name.

    Returns:
        The parts of ``name``: lower-cased text at even positions, integers at odd ones.
    """
    return [int(p) if p.isdigit() else p.lower() for p in _DIGITS.split(name)]
