"""Reflective walls: mirror images of the animal in the arena's acrylic walls.

A wall is a partial mirror: a pixel that shows wall ``i`` also shows, blended with the
wall's reflectivity, whatever its ray would hit after reflecting off the wall's plane. That
is the same as the straight ray hitting the animal mirrored across the plane, behind the
wall; so each frame the animal's ellipsoids are mirrored across each wall the camera sees
and intersected exactly, only behind the wall (the renderer's ``beyond_background``).
The labels stay those of the real animal.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from freipose.synth.body import BodyGeometry


class WallMirror:
    """The mirror images of one camera's walls (see the module docstring).

    Args:
        renderer: the camera's ``freipose.synth.render.CameraRenderer`` (which creates the
            mirror; its ``style.reflections`` is the reflectivity).
    """

    def __init__(self, renderer: Any) -> None:
        self.renderer = renderer
        hx, hy = renderer.arena.half
        self.planes = ((0, hx), (0, -hx), (1, hy), (1, -hy))  # (axis, value) of walls 0..3
        self.walls = [i for i in range(4) if np.any(renderer.wall_id == i)]

    def mirrored(self, geom: BodyGeometry, f: int, wall: int) -> tuple[np.ndarray, ...]:
        """Frame ``f`` mirrored across ``wall``: centres (N, 3), axes (N, 3, 3), radii (N, 3)."""
        axis, value = self.planes[wall]
        C = geom.centers[f].copy()
        C[:, axis] = 2 * value - C[:, axis]
        A = geom.axes[f].copy()
        A[:, axis, :] *= -1.0  # the local axes' world coordinates, mirrored
        return C, A, geom.radii[f]

    def background(
        self, geom: BodyGeometry, f: int, palette: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """The frame's background with the mirror images: (linear (H, W, 3), uint8), or None.

        None: no mirror image is in view (the static background applies).
        """
        r = self.renderer
        k = np.float32(r.style.reflections)
        out = None
        for wall in self.walls:
            C, A, Rr = self.mirrored(geom, f, wall)
            ab = r._animal_box(C, Rr.max(axis=1))
            if ab is None:
                continue
            hits = r._intersect(C, A, Rr, ab, beyond_background=True)
            x0, y0, x1, y1 = ab.box
            mask = (hits.pid >= 0) & (r.wall_id[y0:y1, x0:x1] == wall)
            if not mask.any():
                continue
            rgb = r._shade(geom.materials, A, Rr, palette, hits, ab.box)
            if out is None:
                out = r.bg_lin.copy()
            sub = out[y0:y1, x0:x1]
            sub[mask] = (1 - k) * sub[mask] + k * rgb[mask]
        if out is None:
            return None
        return out, r.style.to_u8(out)


__all__ = ["WallMirror"]
