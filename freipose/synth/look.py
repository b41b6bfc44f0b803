"""Photometric settings of the synthetic cameras and scene, and the floor textures.

:class:`CameraLook` is drawn per camera (exposure gain, white balance, noise, vignetting);
:class:`SceneStyle` holds the scene's settings (grayscale sensor, floor texture and colours,
brightness, contrast, illumination gradient, defocus blur, noise level, wall reflectivity);
its defaults reproduce the classic scene exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, cast

import cv2
import numpy as np


@dataclass(frozen=True)
class CameraLook:
    """Per-camera photometric settings: exposure gain, white balance, noise, vignetting."""

    gain: float = 1.0
    white_balance: tuple[float, float, float] = (1.0, 1.0, 1.0)
    noise_sigma: float = 2.0
    vignetting: float = 0.2

    @classmethod
    def random(cls, rng: np.random.Generator) -> CameraLook:
        """A random look: gain, white balance, noise and vignetting drawn from ``rng``."""
        return cls(
            gain=float(rng.uniform(0.82, 1.15)),
            white_balance=cast(
                "tuple[float, float, float]",
                tuple(float(v) for v in rng.uniform(0.94, 1.06, size=3)),
            ),
            noise_sigma=float(rng.uniform(1.5, 3.5)),
            vignetting=float(rng.uniform(0.1, 0.3)),
        )


@dataclass(frozen=True)
class SceneStyle:
    """Scene-wide photometric settings of one camera's images (defaults: the classic scene).

    Attributes:
        grayscale: a monochrome sensor: every pixel has R = G = B.
        floor: ``"mat"`` (mottled mat) or ``"bedding"`` (coarse grains of litter).
        floor_color: RGB 0..1 of the floor (None: the mat's grey or the bedding's beige).
        wall_color: RGB 0..1 of the walls (None: light grey).
        brightness: factor on the exposure.
        contrast: factor on the deviation from mid grey (linear intensities).
        light_gradient: strength of a linear illumination gradient across the image
            (its direction drawn per camera).
        blur: Gaussian defocus blur of the whole image (sigma, px; 0: none).
        noise_level: factor on the sensor noise.
        reflections: reflectivity of the walls (0: no mirror images of the animal).
        walls: ``"opaque"`` or ``"acrylic"`` (transparent: the animal is seen through them).
    """

    grayscale: bool = False
    floor: str = "mat"
    floor_color: tuple[float, float, float] | None = None
    wall_color: tuple[float, float, float] | None = None
    brightness: float = 1.0
    contrast: float = 1.0
    light_gradient: float = 0.0
    blur: float = 0.0
    noise_level: float = 1.0
    reflections: float = 0.0
    walls: str = "opaque"

    def to_u8(self, lin: np.ndarray) -> np.ndarray:
        """uint8 image of linear intensities ``lin`` (..., 3) after the contrast."""
        if self.contrast != 1.0:
            lin = 0.5 + (lin - 0.5) * np.float32(self.contrast)
        return np.clip(lin * 255 + 0.5, 0, 255).astype(np.uint8)

    def sensor(self, img: np.ndarray) -> np.ndarray:
        """The final uint8 BGR image (H, W, 3) as the sensor gives it: grayscale if so."""
        if not self.grayscale:
            return img
        gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        return cv2.merge([gray, gray, gray])


def bgr(rgb: tuple[float, float, float] | None, default: Any) -> np.ndarray:
    """(3,) BGR of the RGB colour ``rgb``, or ``default`` (BGR) when it is None."""
    if rgb is None:
        return np.asarray(default, dtype=np.float64)
    return np.asarray(rgb[::-1], dtype=np.float64)


def mat_texture(rng: np.random.Generator, extent: float, ppm: float) -> np.ndarray:
    """Grayscale multiplier texture (S, S) float32 around 1 for the floor: mottled mat."""
    size = int(round(2 * extent * ppm))
    tex = np.ones((size, size), np.float32)
    for cells, amp in ((6, 0.08), (25, 0.06), (90, 0.05), (size // 3, 0.06)):
        small = rng.normal(size=(cells, cells)).astype(np.float32)
        tex += amp * cv2.resize(small, (size, size), interpolation=cv2.INTER_CUBIC)
    return tex


def bedding_texture(rng: np.random.Generator, extent: float, ppm: float) -> np.ndarray:
    """Grayscale multiplier texture (S, S) float32 around 1: bedding of 2-8 mm grains.

    Random chips (bright and dark, elongated, overlapping) over a coarse mottling, with
    strong contrast: the animal's paws and belly sink into a busy background.
    """
    size = int(round(2 * extent * ppm))
    tex = np.ones((size, size), np.float32)
    for cells, amp in ((8, 0.10), (40, 0.08)):
        small = rng.normal(size=(cells, cells)).astype(np.float32)
        tex += amp * cv2.resize(small, (size, size), interpolation=cv2.INTER_CUBIC)
    n = int(size * size / (25.0 * ppm * ppm))  # about one chip per 5 x 5 mm
    centres = rng.uniform(0, size, size=(n, 2))
    lengths = rng.uniform(2.0, 8.0, n) * ppm
    widths = lengths * rng.uniform(0.3, 0.7, n)
    angles = rng.uniform(0, 180, n)
    shades = rng.normal(0.0, 0.35, n)
    chips = np.zeros((size, size), np.float32)
    for (cx, cy), a, b, ang, sh in zip(centres, lengths, widths, angles, shades):
        cv2.ellipse(chips, (int(cx), int(cy)), (max(1, int(a / 2)), max(1, int(b / 2))),
                    float(ang), 0, 360, float(sh), -1)  # fmt: skip
    chips = cv2.GaussianBlur(chips, (0, 0), 0.6 * ppm)
    return np.clip(tex + chips, 0.3, 1.8).astype(np.float32)


def gradient_map(rng: np.random.Generator, size: tuple[int, int], strength: float) -> np.ndarray:
    """(H, W) float32 illumination factor: a linear ramp of +-``strength`` across the image."""
    w, h = size
    ang = rng.uniform(0, 2 * np.pi)
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    ramp = ((uu - (w - 1) / 2) * np.cos(ang) + (vv - (h - 1) / 2) * np.sin(ang)) / (
        0.5 * np.hypot(w, h)
    )
    return np.clip(1.0 + strength * ramp, 0.05, 2.0).astype(np.float32)


def value_noise_table(rng: np.random.Generator, n: int = 16) -> np.ndarray:
    """(n, n, n) float32 lattice values in [-1, 1] for :func:`value_noise3`."""
    return rng.uniform(-1.0, 1.0, size=(n, n, n)).astype(np.float32)


def value_noise3(table: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Smooth periodic 3D value noise in [-1, 1] at points p (..., 3) (lattice spacing 1)."""
    n = table.shape[0]
    f = np.floor(p)
    w = p - f
    w = w * w * (3 - 2 * w)
    i = f.astype(np.int64) % n
    j = (i + 1) % n
    out: Any = 0.0
    for dx in (0, 1):
        ix = j[..., 0] if dx else i[..., 0]
        wx = w[..., 0] if dx else 1 - w[..., 0]
        for dy in (0, 1):
            iy = j[..., 1] if dy else i[..., 1]
            wy = w[..., 1] if dy else 1 - w[..., 1]
            for dz in (0, 1):
                iz = j[..., 2] if dz else i[..., 2]
                wz = w[..., 2] if dz else 1 - w[..., 2]
                out = out + table[ix, iy, iz] * (wx * wy * wz)
    return out


def blur_kernel(blur_px: np.ndarray | None, sigma: float = 0.55) -> np.ndarray:
    """Normalized kernel: a motion of ``blur_px`` (dx, dy) pixels convolved with optics blur."""
    dx, dy = (0.0, 0.0) if blur_px is None else (float(v) for v in blur_px)
    length = math.hypot(dx, dy)
    if not np.isfinite(length):
        length = 0.0
    length = min(length, 12.0)
    k = 2 * int(math.ceil(length / 2 + 2 * sigma)) + 1
    ker = np.zeros((k, k), np.float32)
    c = (k - 1) / 2
    n = max(1, int(math.ceil(length * 3)))
    ux, uy = (dx / math.hypot(dx, dy), dy / math.hypot(dx, dy)) if length > 0 else (1.0, 0.0)
    for s in np.linspace(-length / 2, length / 2, n) if n > 1 else [0.0]:
        x, y = c + s * ux, c + s * uy
        xi, yi = int(math.floor(x)), int(math.floor(y))
        fx, fy = x - xi, y - yi
        for ddx, ddy, wgt in (
            (0, 0, (1 - fx) * (1 - fy)),
            (1, 0, fx * (1 - fy)),
            (0, 1, (1 - fx) * fy),
            (1, 1, fx * fy),
        ):
            if 0 <= xi + ddx < k and 0 <= yi + ddy < k:
                ker[yi + ddy, xi + ddx] += wgt
    blurred = cv2.GaussianBlur(ker, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
    return blurred / blurred.sum()


__all__ = [
    "CameraLook",
    "SceneStyle",
    "bedding_texture",
    "bgr",
    "blur_kernel",
    "gradient_map",
    "mat_texture",
    "value_noise3",
    "value_noise_table",
]
