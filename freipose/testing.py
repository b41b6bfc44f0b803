"""Small, hand-checkable test fixtures that users and tests share (no files, no randomness)."""

from __future__ import annotations

import glob
import re
import shlex

import numpy as np

from freipose.geometry import Camera, CameraRig


def make_circle_rig(
    n: int = 6,
    radius: float = 1000.0,
    height: float = 600.0,
    size: tuple[int, int] = (640, 480),
    focal: float = 800.0,
    distortion: bool = False,
) -> CameraRig:
    """``n`` cameras evenly spaced on a circle of ``radius`` mm at ``height`` mm.

    The cameras look at the origin, z up. With ``distortion`` each camera gets a mild,
    different lens distortion.
    """
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        pos = (radius * np.cos(a), radius * np.sin(a), height)
        dist = (
            np.array([-0.12 + 0.02 * i, 0.05, 0.001 * (i - 2), -0.0005 * i, -0.01])
            if distortion
            else None
        )
        cams.append(Camera.look_at(f"cam{i}", pos, (0, 0, 0), size, focal, dist=dist))
    return CameraRig(tuple(cams), {"world": "origin at the arena centre, z up"})


_FENCED = re.compile(r"(?:<!-- file: (\S+) -->\n)?```(\w+)\n(.*?)```", re.S)


def fenced_blocks(text: str) -> list[tuple[str, str, str | None]]:
    """The fenced code blocks of a Markdown page, in order.

    A block preceded by a ``<!-- file: NAME -->`` line is a file the reader writes.

    Returns:
        (language, body, file name or None) per block.
    """
    return [(m.group(2), m.group(3), m.group(1)) for m in _FENCED.finditer(text)]


def freipose_commands(body: str) -> list[list[str]]:
    """The ``freipose`` commands of a bash block as argument lists, without ``freipose``.

    Continuation lines are joined, comments dropped and globs expanded against the current
    folder (a glob with no match stays as written).

    Raises:
        ValueError: a line runs another program than ``freipose``.
    """
    cmds = []
    for line in body.replace("\\\n", " ").splitlines():
        line = line.split(" #")[0].strip()
        if not line or line.startswith("#"):
            continue
        args = shlex.split(line)
        if args[0] != "freipose":
            raise ValueError(f"expected only freipose commands in the block, found: {line}")
        expanded: list[str] = []
        for a in args[1:]:
            hits = sorted(glob.glob(a)) if any(ch in a for ch in "*?[") else []
            expanded += hits or [a]
        cmds.append(expanded)
    return cmds
