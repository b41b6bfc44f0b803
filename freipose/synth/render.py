"""Exact inverse-mapping renderer for one camera: arena background plus the ellipsoid animal.

Every pixel's undistorted viewing ray is computed once per camera (``pixel_to_ray``), so
the rendering is exact for the pinhole-plus-distortion model: a pixel shows what its ray
hits first. Rays are intersected analytically with the floor plane, the four arena walls
(rendered once per camera into a static background with its depth) and, per frame, with
the animal's ellipsoids — only for the pixels inside the projected bounding box of each
part (bounding-sphere culling). The frame adds Lambert shading with a directional light,
fur texture (3D value noise), a soft contact shadow, per-camera exposure/white balance and
vignetting, mild motion blur (directional kernel composited over the static background),
and sensor noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from freipose.geometry import (
    Camera,
    distort_normalized,
    pixel_to_ray,
    project,
    remove_intrinsics,
    undistort_normalized,
)
from freipose.synth.body import PART, BodyGeometry, per_animal_parts
from freipose.synth.coats import FURRY, MAT, MATERIALS, fur_pattern
from freipose.synth.look import (
    CameraLook,
    SceneStyle,
    bedding_texture,
    bgr,
    blur_kernel,
    gradient_map,
    mat_texture,
    value_noise3,
    value_noise_table,
)
from freipose.synth.mirror import acrylic_walls
from freipose.synth.rig import ArenaConfig

LIGHT = np.array([0.35, -0.25, 1.0]) / np.linalg.norm([0.35, -0.25, 1.0])
LIGHT.setflags(write=False)
_SHADOW_PARTS = (PART["haunch"], PART["chest"], PART["head"], PART["neck"])
_CONTACT_PARTS = (PART["paw_front_r"], PART["paw_front_l"], PART["foot_r"], PART["foot_l"])

BG_NONE, BG_FLOOR, BG_WALL = 0, 1, 2


def pixel_rays(uv: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Exact unit world rays through pixels ``uv`` (..., 2): ``(origin (3,), dirs (..., 3))``.

    Same as ``freipose.geometry.pixel_to_ray`` but faster for whole images: few fixed-point
    iterations then Newton; falls back to the full solver if the residual is not tiny.
    """
    xy_d = remove_intrinsics(uv, camera.K)
    xy = undistort_normalized(xy_d, camera.dist, iterations=5)
    if camera.has_distortion:
        res = np.abs(distort_normalized(xy, camera.dist) - xy_d).max()
        if not res < 1e-12:
            return pixel_to_ray(uv, camera)
    d = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1) @ camera.R
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return camera.center, d


@dataclass(frozen=True, eq=False)
class _AnimalBox:
    """Where the animal and its shadow can be seen in one frame.

    Attributes:
        boxes: (N + S, 4) integer boxes x0, y0, x1, y1 (exclusive) of the N parts and the S
            shadow blobs.
        valid: (N + S,) the box is not empty.
        shadow_centres: (S, 3) floor centres of the shadow blobs, mm.
        box: (x0, y0, x1, y1) the union of the valid boxes.
    """

    boxes: np.ndarray
    valid: np.ndarray
    shadow_centres: np.ndarray
    box: tuple[int, int, int, int]


@dataclass(frozen=True, eq=False)
class _Hits:
    """The animal's ray hits in a box of h x w pixels.

    Attributes:
        pid: (h, w) id of the part seen, -1 where the background is seen.
        loc: (3, h, w) float32 hit points in the unit-sphere frame of the part.
    """

    pid: np.ndarray
    loc: np.ndarray


class CameraRenderer:
    """Renders frames of one camera (see the module docstring).

    Args:
        camera: the camera.
        arena: the arena.
        seed: seed of this camera's textures, look and noise.
        look: photometric settings (default: random from ``seed``).
    """

    def __init__(
        self,
        camera: Camera,
        arena: ArenaConfig,
        seed: int,
        look: CameraLook | None = None,
        style: SceneStyle | None = None,
    ) -> None:
        self.camera = camera
        self.arena = arena
        self.style = style or SceneStyle()
        rng = np.random.default_rng(seed)
        self.look = look or CameraLook.random(rng)
        w, h = camera.size
        uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        origin, dirs = pixel_rays(np.stack([uu, vv], -1), camera)
        self.origin = origin
        self.rays_soa = np.ascontiguousarray(
            np.moveaxis(dirs, -1, 0), dtype=np.float32
        )  # (3, H, W)
        # photometric maps
        r2 = ((uu - (w - 1) / 2) ** 2 + (vv - (h - 1) / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
        self.shade = (
            (1.0 - self.look.vignetting * r2)[..., None]
            * self.look.gain
            * np.asarray(self.look.white_balance)
        ).astype(np.float32)  # (H, W, 3) exposure x white balance x vignetting
        if self.style.brightness != 1.0:
            self.shade *= np.float32(self.style.brightness)
        if self.style.light_gradient > 0:
            g_rng = np.random.default_rng(seed + 104729)
            self.shade *= gradient_map(g_rng, (w, h), self.style.light_gradient)[..., None]
        self.fur_noise = value_noise_table(np.random.default_rng(seed + 7919))
        self._background(rng, dirs)
        pad = 24
        sigma = self.look.noise_sigma * self.style.noise_level
        noise = rng.normal(0, sigma, size=(h + pad, w + pad, 3))
        noise = np.clip(np.round(noise), -255, 255)
        self.noise_pos = np.clip(noise, 0, 255).astype(np.uint8)
        self.noise_neg = np.clip(-noise, 0, 255).astype(np.uint8)
        self.pad = pad
        self._ray_du: np.ndarray | None = None  # ray derivatives (board anti-aliasing)
        self._ray_dv: np.ndarray | None = None
        self._mirror: Any = None  # the walls' mirror images (freipose.synth.mirror), on first use

    def ray_derivatives(self) -> tuple[np.ndarray, np.ndarray]:
        """(3, H, W) float32 change of the pixel rays per pixel along u and along v.

        Computed on first use and kept (the calibration board's anti-aliasing needs them).
        """
        if self._ray_du is None or self._ray_dv is None:
            self._ray_du = np.gradient(self.rays_soa, axis=2).astype(np.float32)
            self._ray_dv = np.gradient(self.rays_soa, axis=1).astype(np.float32)
        return self._ray_du, self._ray_dv

    # -- static background -------------------------------------------------------------------
    def _background(self, rng: np.random.Generator, dirs: np.ndarray) -> None:
        """The static background: its depth, floor points, kinds, wall ids and colours.

        Floor, walls, table and room; the floor is transparent inside the arena for a
        camera below it.
        """
        o = self.origin
        h, w = dirs.shape[:2]
        hx, hy = self.arena.half
        wh = self.arena.wall_height
        t_best = np.full((h, w), np.inf)
        kind = np.full((h, w), BG_NONE, np.int8)
        normal = np.zeros((h, w, 3))
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -o[2] / dirs[..., 2]
        hitp = o + t[..., None] * dirs
        ok = (t > 0) & (np.abs(hitp[..., 0]) < 4000) & (np.abs(hitp[..., 1]) < 4000)
        through = np.zeros((h, w), bool)  # seen through the transparent floor (from below)
        if o[2] < 0:
            through = ok & (np.abs(hitp[..., 0]) <= hx) & (np.abs(hitp[..., 1]) <= hy)
            ok &= ~through
        t_best[ok] = t[ok]
        kind[ok] = BG_FLOOR
        normal[ok] = (0, 0, 1)
        self.wall_id = np.full((h, w), -1, np.int8)  # which wall (0..3) a wall pixel shows
        self.acrylic = None
        if self.style.walls == "acrylic":  # transparent panes: not in the depth buffer
            self.acrylic = acrylic_walls(o, dirs, self.arena, t_best)
            self.wall_id = self.acrylic.inner_id
        opaque = ((0, hx), (0, -hx), (1, hy), (1, -hy)) if self.acrylic is None else ()
        for wall, (axis, val) in enumerate(opaque):
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (val - o[axis]) / dirs[..., axis]
            p = o + t[..., None] * dirs
            other = 1 - axis
            lim = hy if axis == 0 else hx
            ok = (
                (t > 0)
                & (t < t_best)
                & (np.abs(p[..., other]) <= lim)
                & (p[..., 2] >= 0)
                & (p[..., 2] <= wh)
            )
            t_best[ok] = t[ok]
            kind[ok] = BG_WALL
            self.wall_id[ok] = wall
            n = np.zeros(3)
            n[axis] = 1.0
            side = np.where((dirs[..., axis] > 0)[..., None], -n, n)  # normal facing the camera
            normal[ok] = side[ok]
        self.bg_depth = np.where(kind != BG_NONE, t_best, np.inf).astype(np.float32)
        # where a mirror image behind a wall starts (the walls' reflections)
        self.mirror_depth = self.bg_depth if self.acrylic is None else self.acrylic.inner_depth
        hit = o + np.where(np.isfinite(t_best), t_best, 0)[..., None] * dirs
        self.floor_xy = np.where((kind == BG_FLOOR)[..., None], hit[..., :2], np.nan).astype(
            np.float32
        )
        self.bg_kind = kind
        col = self._background_colours(rng, hit, kind, normal)
        col[through] *= 0.85  # the acrylic floor dims what is seen through it
        lin = (col * self.shade).astype(np.float32)
        self.bg_lin = cv2.GaussianBlur(lin, (0, 0), 0.6)
        self.bg_u8 = self.style.to_u8(self.through_walls(self.bg_lin))

    def through_walls(
        self, lin: np.ndarray, box: tuple[int, int, int, int] | None = None
    ) -> np.ndarray:
        """Linear ``lin`` (h, w, 3) of ``box`` (None: all) seen through acrylic walls (if any)."""
        if self.acrylic is None:
            return lin
        wall = bgr(self.style.wall_color, (0.66, 0.68, 0.68))
        return self.acrylic.apply(lin, box or (0, 0, lin.shape[1], lin.shape[0]), wall, self.shade)

    def _background_colours(
        self, rng: np.random.Generator, hit: np.ndarray, kind: np.ndarray, normal: np.ndarray
    ) -> np.ndarray:
        """(H, W, 3) BGR albedo x light of the background at the hit points ``hit`` (H, W, 3)."""
        h, w = kind.shape
        hx, hy = self.arena.half
        wh = self.arena.wall_height
        extent = max(hx, hy) + 60.0
        style = self.style
        if style.floor == "bedding":
            ppm = float(np.clip(max(self.camera.size) / (2 * extent), 1.0, 4.0))
            tex = bedding_texture(rng, extent, ppm)
            default_floor = (0.45, 0.62, 0.72)  # beige (BGR)
        else:
            ppm = 1.0
            tex = mat_texture(rng, extent, ppm)
            default_floor = (0.40, 0.42, 0.44)
        mx = ((hit[..., 0] + extent) * ppm - 0.5).astype(np.float32)
        my = ((hit[..., 1] + extent) * ppm - 0.5).astype(np.float32)
        floor_t = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        base_floor = bgr(style.floor_color, default_floor) * rng.uniform(0.9, 1.1)
        table = np.array([0.18, 0.2, 0.24])
        inside = (np.abs(hit[..., 0]) <= hx) & (np.abs(hit[..., 1]) <= hy)
        col = np.empty((h, w, 3))
        col[:] = (0.22, 0.22, 0.22)  # the room beyond
        lam_floor = 0.45 + 0.55 * LIGHT[2]
        fl = kind == BG_FLOOR
        table_t = floor_t if style.floor == "mat" else 1 + 0.25 * (floor_t - 1)  # no bedding
        floor_col = np.where(inside[..., None], base_floor * floor_t[..., None],
                             table * table_t[..., None]) * lam_floor  # fmt: skip
        col[fl] = floor_col[fl]
        wl = kind == BG_WALL
        wall_base = bgr(style.wall_color, (0.66, 0.68, 0.68))
        lam = 0.5 + 0.5 * np.clip(normal @ LIGHT, 0, 1)
        hz = np.clip(hit[..., 2] / max(wh, 1.0), 0, 1)
        wall_col = (
            wall_base * (lam * (0.85 + 0.15 * hz))[..., None] * (0.97 + 0.03 * floor_t[..., None])
        )
        col[wl] = wall_col[wl]
        return col

    # -- animal ------------------------------------------------------------------------------
    def _part_boxes(self, centers: np.ndarray, radii_max: np.ndarray) -> np.ndarray:
        """(N, 4) integer boxes x0, y0, x1, y1 (exclusive) of the parts' bounding spheres."""
        cam = self.camera
        R = cam.R
        n = len(centers)
        offs = np.concatenate([R[0:1], -R[0:1], R[1:2], -R[1:2]])  # camera x/y axes in world
        pts = centers[:, None, :] + radii_max[:, None, None] * offs[None]
        uv = project(np.concatenate([centers[:, None], pts], 1), cam)  # (N, 5, 2)
        depth = centers @ R[2] + cam.t[2]
        boxes = np.zeros((n, 4), np.int64)
        w, h = cam.size
        bad = ~np.all(np.isfinite(uv), axis=(1, 2)) | (depth <= radii_max * 1.05)
        lo = np.nanmin(uv, axis=1)
        hi = np.nanmax(uv, axis=1)
        m = 0.15 * (hi - lo).max(axis=1, keepdims=True) + 2.0
        lo = np.floor(lo - m)
        hi = np.ceil(hi + m) + 1
        boxes[:, 0] = np.clip(np.nan_to_num(lo[:, 0]), 0, w)
        boxes[:, 1] = np.clip(np.nan_to_num(lo[:, 1]), 0, h)
        boxes[:, 2] = np.clip(np.nan_to_num(hi[:, 0]), 0, w)
        boxes[:, 3] = np.clip(np.nan_to_num(hi[:, 1]), 0, h)
        boxes[bad] = 0
        return boxes

    def _animal_box(self, C: np.ndarray, rmax: np.ndarray) -> _AnimalBox | None:
        """Image boxes of the parts and of their shadow blobs (None: none is in the image).

        Args:
            C: (N, 3) part centres, mm.
            rmax: (N,) bounding radii of the parts, mm.
        """
        sh_idx = per_animal_parts(_SHADOW_PARTS + _CONTACT_PARTS, len(C))
        shift = -LIGHT[:2] / LIGHT[2]
        sh_c = np.concatenate(
            [C[sh_idx, :2] + shift * C[sh_idx, 2:3], np.zeros((len(sh_idx), 1))], 1
        )
        boxes = self._part_boxes(
            np.concatenate([C, sh_c]), np.concatenate([rmax, 1.7 * rmax[sh_idx]])
        )
        valid = (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
        if not valid[: len(C)].any() and not valid.any():
            return None
        x0, y0 = boxes[valid, 0].min(), boxes[valid, 1].min()
        x1, y1 = boxes[valid, 2].max(), boxes[valid, 3].max()
        return _AnimalBox(boxes, valid, sh_c, (x0, y0, x1, y1))

    def _intersect(
        self,
        C: np.ndarray,
        A: np.ndarray,
        Rr: np.ndarray,
        ab: _AnimalBox,
        beyond_background: bool = False,
    ) -> _Hits:
        """The first part each pixel's ray hits in front of the background, and where.

        All (pixel, part) candidate pairs (the pixels inside each part's box) are
        intersected at once with the parts' ellipsoids (centres ``C`` (N, 3), axes
        ``A`` (N, 3, 3), radii ``Rr`` (N, 3)). ``beyond_background``: only hits behind the
        wall a pixel shows count instead (a mirror image seen in the wall).
        """
        x0, y0, x1, y1 = ab.box
        bh, bw = y1 - y0, x1 - x0
        parts = np.flatnonzero(ab.valid[: len(C)])
        pb = ab.boxes[parts]
        counts = (pb[:, 2] - pb[:, 0]) * (pb[:, 3] - pb[:, 1])
        rows = [(np.arange(b[1], b[3]) - y0)[:, None] * bw for b in pb]
        cols = [(np.arange(b[0], b[2]) - x0)[None, :] for b in pb]
        pix = np.concatenate([(r + c).ravel() for r, c in zip(rows, cols)] + [np.zeros(0, int)])
        M = (A[parts] / Rr[parts][:, None, :]).astype(np.float32)  # d @ M: unit-sphere frame
        op = np.einsum("ni,nij->nj", self.origin - C[parts], A[parts] / Rr[parts][:, None, :])
        cc = (np.sum(op * op, axis=1) - 1.0).astype(np.float32)
        Mr = np.repeat(M.reshape(-1, 9), counts, axis=0)
        opr = np.repeat(op.astype(np.float32), counts, axis=0)
        ray = self.rays_soa[:, y0:y1, x0:x1].reshape(3, -1)
        Dx, Dy, Dz = ray[0][pix], ray[1][pix], ray[2][pix]
        dpx = Mr[:, 0] * Dx + Mr[:, 3] * Dy + Mr[:, 6] * Dz
        dpy = Mr[:, 1] * Dx + Mr[:, 4] * Dy + Mr[:, 7] * Dz
        dpz = Mr[:, 2] * Dx + Mr[:, 5] * Dy + Mr[:, 8] * Dz
        a = dpx * dpx + dpy * dpy + dpz * dpz
        b = dpx * opr[:, 0] + dpy * opr[:, 1] + dpz * opr[:, 2]
        disc = b * b - a * np.repeat(cc, counts)
        hit = disc > 0
        sdist = (-b - np.sqrt(np.maximum(disc, 0))) / a
        sdist = np.where(hit & (sdist > 0), sdist, np.float32(np.inf))
        zflat = self.bg_depth[y0:y1, x0:x1].ravel().copy()
        if beyond_background:
            near = self.mirror_depth[y0:y1, x0:x1].ravel()
            sdist = np.where(sdist > near[pix], sdist, np.float32(np.inf))
            zflat[:] = np.inf
        np.minimum.at(zflat, pix, sdist)
        win = np.flatnonzero(np.isfinite(sdist) & (sdist <= zflat[pix]))
        pid_flat = np.full(bh * bw, -1, np.int64)
        pid_flat[pix[win]] = np.repeat(parts, counts)[win]
        loc = np.zeros((3, bh * bw), np.float32)
        sw = sdist[win]
        loc[0, pix[win]] = opr[win, 0] + sw * dpx[win]
        loc[1, pix[win]] = opr[win, 1] + sw * dpy[win]
        loc[2, pix[win]] = opr[win, 2] + sw * dpz[win]
        return _Hits(pid_flat.reshape(bh, bw), loc.reshape(3, bh, bw))

    def _shade(
        self,
        materials: np.ndarray,
        A: np.ndarray,
        Rr: np.ndarray,
        palette: np.ndarray,
        hits: _Hits,
        box: tuple[int, int, int, int],
    ) -> np.ndarray:
        """(h, w, 3) linear BGR of the hit pixels (zero elsewhere).

        Lambert shading plus a view term, fur texture moving with each part, the hooded
        rat's fur pattern and specular eyes and nose, times the camera's exposure map.
        """
        x0, y0, x1, y1 = box
        pid, loc = hits.pid, hits.loc
        rgb = np.zeros((y1 - y0, x1 - x0, 3), np.float32)
        m = pid >= 0
        if not m.any():
            return rgb
        ids = pid[m]
        p = loc[:, m].T.astype(np.float64)  # (m, 3) unit-sphere coordinates
        mats = materials[ids]  # several animals: animal a's materials are offset by a * M
        kind = mats % len(MATERIALS)
        u = p / Rr[ids]
        Ag = A[ids]
        n = (Ag * u[:, None, :]).sum(-1)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        d = self.rays_soa[:, y0:y1, x0:x1][:, m].T.astype(np.float64)
        q = (p * Rr[ids]).astype(np.float32)  # local mm: texture moves with the part
        fur = value_noise3(self.fur_noise, q / 1.7)
        second = fur_pattern(kind, ids, p, q, self.fur_noise)
        alb = palette[mats, second.astype(np.int64)]
        furry = np.isin(kind, FURRY)
        alb = alb * (1.0 + np.where(furry, 0.13, 0.05) * fur)[:, None]
        ndl = np.clip(n @ LIGHT, 0, 1)
        ndv = np.clip(-(n * d).sum(1), 0, 1)
        lum = 0.32 + 0.68 * ndl + 0.12 * ndv
        col = alb * lum[:, None]
        shiny = np.isin(kind, (MAT["eye"], MAT["nose"]))
        if shiny.any():
            hv = LIGHT - d[shiny]
            hv /= np.linalg.norm(hv, axis=1, keepdims=True)
            spec = np.clip((n[shiny] * hv).sum(1), 0, 1) ** 25
            col[shiny] += 0.7 * spec[:, None]
        rgb[m] = (col * self.shade[y0:y1, x0:x1][m]).astype(np.float32)
        return rgb

    def _shadow(self, C: np.ndarray, A: np.ndarray, Rr: np.ndarray, ab: _AnimalBox) -> np.ndarray:
        """(h, w) float32 shadow factor of the floor in the box.

        Soft Gaussian blobs under the big parts and the feet, shifted along the light and
        fading with their height.
        """
        x0, y0, x1, y1 = ab.box
        sh_idx = per_animal_parts(_SHADOW_PARTS + _CONTACT_PARTS, len(C))
        n_big = len(_SHADOW_PARTS)
        fxy = self.floor_xy[y0:y1, x0:x1]
        shadow = np.ones((y1 - y0, x1 - x0), np.float32)
        if not np.isfinite(fxy[..., 0]).any():
            return shadow
        for k, i in enumerate(sh_idx):
            bx0, by0, bx1, by1 = ab.boxes[len(C) + k]
            if bx1 <= bx0 or by1 <= by0:
                continue
            sub = (slice(by0 - y0, by1 - y0), slice(bx0 - x0, bx1 - x0))
            gx, gy = fxy[sub][..., 0], fxy[sub][..., 1]
            cov = (A[i] * Rr[i] ** 2) @ A[i].T
            sxx, sxy, syy = cov[0, 0], cov[0, 1], cov[1, 1]
            sc = (1.15 + 0.004 * C[i, 2]) ** 2
            det = (sxx * syy - sxy * sxy) * sc * sc
            ia, ib, ic = syy * sc / det, -sxy * sc / det, sxx * sc / det
            dx = gx - np.float32(ab.shadow_centres[k, 0])
            dy = gy - np.float32(ab.shadow_centres[k, 1])
            qf = np.float32(ia) * dx * dx + np.float32(2 * ib) * dx * dy + np.float32(ic) * dy * dy
            big = k % (n_big + len(_CONTACT_PARTS)) < n_big
            strength = (0.5 if big else 0.4) * math.exp(-C[i, 2] / 150.0)
            blob = 1.0 - np.float32(strength) * np.exp(np.float32(-2.0) * qf)
            shadow[sub] *= np.where(np.isfinite(blob), blob, np.float32(1.0))
        return shadow

    def _composite(
        self,
        rgb: np.ndarray,
        mask: np.ndarray,
        shadow: np.ndarray,
        box: tuple[int, int, int, int],
        blur_px: np.ndarray | None,
        background: np.ndarray | None = None,
    ) -> np.ndarray:
        """(h, w, 3) linear BGR of the box: the animal motion-blurred over its background.

        Args:
            rgb: (h, w, 3) the animal's colours (where ``mask``).
            mask: (h, w) pixels that show the animal.
            shadow: (h, w) shadow factor of the background.
            box: (x0, y0, x1, y1) the box in the image.
            blur_px: (2,) image motion during the exposure, px, or None.
            background: (H, W, 3) linear background of this frame (None: the static one).
        """
        x0, y0, x1, y1 = box
        bh, bw = mask.shape
        bg = self.bg_lin if background is None else background
        out = bg[y0:y1, x0:x1] * shadow[..., None]
        if not mask.any():
            return out
        kernel = blur_kernel(blur_px)
        r = kernel.shape[0] // 2 + 1
        rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
        sy = slice(max(0, rows[0] - r), min(bh, rows[-1] + r + 1))
        sx = slice(max(0, cols[0] - r), min(bw, cols[-1] + r + 1))
        alpha = mask[sy, sx].astype(np.float32)
        A_ = cv2.filter2D(
            rgb[sy, sx] * alpha[..., None], -1, kernel, borderType=cv2.BORDER_CONSTANT
        )
        a_ = cv2.filter2D(alpha, -1, kernel, borderType=cv2.BORDER_CONSTANT)
        out[sy, sx] = A_ + (1.0 - a_)[..., None] * out[sy, sx]
        return out

    def render_animal(
        self,
        geom: BodyGeometry,
        f: int,
        palette: np.ndarray,
        blur_px: np.ndarray | None = None,
        background: np.ndarray | None = None,
    ) -> tuple[tuple[int, int, int, int], np.ndarray, np.ndarray] | None:
        """Render frame ``f`` of the animal: ``(box, rgb_linear (h, w, 3), part_id (h, w))``.

        ``box`` is (x0, y0, x1, y1) in the image (exclusive ends); ``part_id`` is -1 where
        the background is seen.

        Args:
            geom: the animal's ellipsoids over all frames.
            f: the frame.
            palette: (n_materials, 2, 3) BGR albedo (``RatBody.palette``).
            blur_px: (2,) image motion during the exposure, px (None: no motion blur).
            background: (H, W, 3) linear background of this frame (None: the static one).

        Returns:
            The rendering, or None when nothing of the animal (or its shadow) is in the
            image.
        """
        C = geom.centers[f]
        A = geom.axes[f]
        Rr = geom.radii[f]
        ab = self._animal_box(C, Rr.max(axis=1))
        if ab is None:
            return None
        hits = self._intersect(C, A, Rr, ab)
        rgb = self._shade(geom.materials, A, Rr, palette, hits, ab.box)
        shadow = self._shadow(C, A, Rr, ab)
        out = self._composite(rgb, hits.pid >= 0, shadow, ab.box, blur_px, background)
        x0, y0, x1, y1 = ab.box
        return (int(x0), int(y0), int(x1), int(y1)), out, hits.pid

    def finish(
        self,
        frame_lin: np.ndarray | None,
        box: tuple[int, int, int, int] | None,
        rng: np.random.Generator,
        background: np.ndarray | None = None,
    ) -> np.ndarray:
        """Compose the final uint8 BGR frame: background, the rendered box, sensor noise.

        Args:
            frame_lin: (h, w, 3) linear BGR of the box, or None.
            box: (x0, y0, x1, y1) of ``frame_lin`` in the image, or None.
            rng: the frame's noise generator.
            background: (H, W, 3) uint8 background of this frame (None: the static one).
        """
        img = (self.bg_u8 if background is None else background).copy()
        if box is not None and frame_lin is not None:
            x0, y0, x1, y1 = box
            img[y0:y1, x0:x1] = self.style.to_u8(self.through_walls(frame_lin, box))
        if self.style.blur > 0:
            img = cv2.GaussianBlur(img, (0, 0), self.style.blur)
        h, w = img.shape[:2]
        oy, ox = (int(v) for v in rng.integers(0, self.pad, size=2))
        img = cv2.add(img, self.noise_pos[oy : oy + h, ox : ox + w])
        oy, ox = (int(v) for v in rng.integers(0, self.pad, size=2))
        img = cv2.subtract(img, self.noise_neg[oy : oy + h, ox : ox + w])
        return self.style.sensor(img)

    def render(
        self,
        geom: BodyGeometry,
        f: int,
        palette: np.ndarray,
        rng: np.random.Generator,
        blur_px: np.ndarray | None = None,
    ) -> np.ndarray:
        """One uint8 BGR frame (H, W, 3) of the animal in frame ``f``.

        With reflective walls (``style.reflections``) the animal's mirror images in the
        walls are blended into the frame's background first.
        """
        bg_lin = bg_u8 = None
        if self.style.reflections > 0:
            from freipose.synth.mirror import WallMirror

            if self._mirror is None:
                self._mirror = WallMirror(self)
            mirrored = self._mirror.background(geom, f, palette)
            if mirrored is not None:
                bg_lin, bg_u8 = mirrored
        res = self.render_animal(geom, f, palette, blur_px, background=bg_lin)
        if res is None:
            return self.finish(None, None, rng, bg_u8)
        box, lin, _ = res
        return self.finish(lin, box, rng, bg_u8)
