"""Small, hand-checkable test fixtures that users and tests share (no files, no randomness)."""

from __future__ import annotations

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
