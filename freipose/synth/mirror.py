"""Reflective walls: mirror images of the animal in the arena's acrylic walls.

A wall is a partial mirror: a pixel that shows wall ``i`` (an opaque wall, or the inner
face of a transparent acrylic one, :func:`acrylic_walls`) also shows, blended with the
wall's reflectivity, whatever its ray would hit after reflecting off the wall's plane. That
is the same as the straight ray hitting the animal mirrored across the plane, behind the
wall; so each frame the animal's ellipsoids are mirrored across each wall the camera sees
and intersected exactly, only behind the wall (the renderer's ``beyond_background``).
The labels stay those of the real animal.
"""

from __future__ import annotations

from dataclasses import dataclass
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
        return out, r.style.to_u8(r.through_walls(out))


@dataclass(frozen=True, eq=False)
class AcrylicWalls:
    """What transparent (acrylic) walls do to the rays of one camera's pixels.

    Attributes:
        transmit: (H, W) float32 share of the light that passes the walls a ray crosses.
        crossings: (H, W) int8 walls crossed before the ray reaches the floor or the room.
        inner_id: (H, W) int8 the nearest wall whose inner face the ray meets (it mirrors
            the animal), -1 where none.
        inner_depth: (H, W) float32 the distance to that face, inf where none.
    """

    transmit: np.ndarray
    crossings: np.ndarray
    inner_id: np.ndarray
    inner_depth: np.ndarray

    def apply(
        self, lin: np.ndarray, box: tuple[int, int, int, int], wall: np.ndarray, shade: np.ndarray
    ) -> np.ndarray:
        """Linear colours ``lin`` (h, w, 3) of image ``box`` as seen through the panes.

        Args:
            lin: (h, w, 3) linear BGR behind the walls.
            box: (x0, y0, x1, y1) of ``lin`` in the image.
            wall: (3,) BGR albedo of the panes (their faint glare).
            shade: (H, W, 3) the camera's exposure map.
        """
        x0, y0, x1, y1 = box
        tr = self.transmit[y0:y1, x0:x1, None]
        glare = self.crossings[y0:y1, x0:x1, None] * np.float32(0.06)
        return lin * tr + glare * wall.astype(np.float32) * shade[y0:y1, x0:x1]


def acrylic_walls(
    origin: np.ndarray, dirs: np.ndarray, arena: Any, t_limit: np.ndarray, loss: float = 0.08
) -> AcrylicWalls:
    """The walls of ``arena`` as transparent panes along the rays ``origin + t dirs``.

    Args:
        origin: (3,) the camera centre.
        dirs: (H, W, 3) unit ray directions.
        arena: the :class:`~freipose.synth.rig.ArenaConfig`.
        t_limit: (H, W) distance to the floor, table or room behind the walls.
        loss: share of the light a pane reflects or absorbs.

    Returns:
        :class:`AcrylicWalls`.
    """
    hx, hy = arena.half
    h, w = dirs.shape[:2]
    crossings = np.zeros((h, w), np.int8)
    inner_id = np.full((h, w), -1, np.int8)
    inner_depth = np.full((h, w), np.inf)
    for wall, (axis, val) in enumerate(((0, hx), (0, -hx), (1, hy), (1, -hy))):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (val - origin[axis]) / dirs[..., axis]
        p = origin + np.nan_to_num(t)[..., None] * dirs
        lim = hy if axis == 0 else hx
        on = (t > 0) & (t < t_limit) & (np.abs(p[..., 1 - axis]) <= lim)
        on &= (p[..., 2] >= 0) & (p[..., 2] <= arena.wall_height)
        crossings += on
        outward = dirs[..., axis] * np.sign(val) > 0  # leaving the box: its inner face
        inner = on & outward & (t < inner_depth)
        inner_id[inner] = wall
        inner_depth[inner] = t[inner]
    transmit = ((1.0 - loss) ** crossings).astype(np.float32)
    return AcrylicWalls(transmit, crossings, inner_id, inner_depth.astype(np.float32))


__all__ = ["AcrylicWalls", "WallMirror", "acrylic_walls"]
