"""Training-time augmentation of one image and its box, and CenterNet targets.

Images are cached at (about) the network's input scale; one random affine map (scale,
translation, i.e. random crops, and flips) takes a cached image to the square network
input, followed by photometric changes: brightness, contrast, saturation, hue, blur and
pixel noise. The box is mapped with the same affine.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from freipose.detect.base import DetectConfigError
from freipose.detect.boxes import clip_boxes, transform_boxes
from freipose.detect.model import STRIDE


@dataclass(frozen=True)
class AugmentConfig:
    """Augmentation strengths (0 disables one).

    Attributes:
        scale: (min, max) zoom relative to letterboxing the whole frame.
        hflip, vflip: probabilities of horizontal / vertical flips.
        color: strength of brightness/contrast/saturation jitter (fraction).
        hue: hue shift in OpenCV hue units (0..180 is a full turn).
        blur: probability of a Gaussian blur (sigma up to 1.5 px).
        noise: standard deviation of additive pixel noise (grey levels), drawn uniformly
            from 0 to this per image.
        random_fill: probability that areas outside the frame are a random colour (else
            the letterbox grey).
        gray: probability of turning the image grey.
    """

    scale: tuple[float, float] = (0.7, 1.5)
    hflip: float = 0.5
    vflip: float = 0.5
    color: float = 0.3
    hue: float = 8.0
    blur: float = 0.3
    noise: float = 6.0
    random_fill: float = 0.5
    gray: float = 0.1

    def __post_init__(self) -> None:
        lo, hi = self.scale
        if not 0 < lo <= hi:
            raise DetectConfigError(
                f"augmentation scale must be (min, max) with 0 < min <= max, got {self.scale}"
            )
        for name in ("hflip", "vflip", "blur", "random_fill", "gray"):
            if not 0 <= getattr(self, name) <= 1:
                raise DetectConfigError(
                    f"{name} is a probability in [0, 1], got {getattr(self, name)}"
                )


def augment(
    image: np.ndarray,
    box: np.ndarray,
    input_size: int,
    cfg: AugmentConfig,
    rng: np.random.Generator,
    out_size: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """A random view of ``image`` (h, w, 3) as a square (O, O, 3) input and its box(es).

    Args:
        image: BGR uint8, at roughly the network scale (longest side about ``input_size``).
        box: (4,) the animal's box in ``image`` pixels, or NaN (no animal in the image);
            or (M, 4) the boxes of several animals (NaN rows: none), one of which is kept
            inside the input.
        input_size: S, the side the whole frame is letterboxed into at zoom 1.
        cfg: augmentation strengths.
        rng: random generator.
        out_size: O, the side of the output (default S); a smaller O gives random crops at
            the network's scale (cheaper training of the fully convolutional network).

    Returns:
        ``(input_image (O, O, 3) uint8, box (4,) or (M, 4))`` with the boxes clipped to the
        output, NaN when there is no animal.
    """
    h, w = image.shape[:2]
    base = input_size / max(w, h)
    size = int(out_size or input_size)
    z = float(np.exp(rng.uniform(np.log(cfg.scale[0]), np.log(cfg.scale[1]))))
    s = base * z
    # Translation: random, but keep the box centre inside the input (random crops).
    tx = rng.uniform(min(0.0, size - w * s), max(0.0, size - w * s))
    ty = rng.uniform(min(0.0, size - h * s), max(0.0, size - h * s))
    rows = np.asarray(box, dtype=np.float64).reshape(-1, 4)
    found = np.flatnonzero(np.isfinite(rows).all(-1))
    has_box = len(found) > 0
    if has_box:
        # the box kept inside: one of several at random (one box: no draw, as ever)
        keep = rows[found[0] if len(found) == 1 else found[rng.integers(len(found))]]
        cx, cy = (keep[0] + keep[2]) / 2, (keep[1] + keep[3]) / 2
        m = 0.15 * size
        lo_x, hi_x = m - (cx + 0.5) * s, size - m - (cx + 0.5) * s
        lo_y, hi_y = m - (cy + 0.5) * s, size - m - (cy + 0.5) * s
        if not lo_x <= tx <= hi_x:
            tx = rng.uniform(lo_x, hi_x)
        if not lo_y <= ty <= hi_y:
            ty = rng.uniform(lo_y, hi_y)
    A = np.array([[s, 0.0, 0.5 * s - 0.5 + tx], [0.0, s, 0.5 * s - 0.5 + ty], [0.0, 0.0, 1.0]])
    if rng.random() < cfg.hflip:
        A = np.array([[-1.0, 0, size - 1], [0, 1, 0], [0, 0, 1]]) @ A
    if rng.random() < cfg.vflip:
        A = np.array([[1.0, 0, 0], [0, -1, size - 1], [0, 0, 1]]) @ A
    fill = (
        tuple(int(v) for v in rng.integers(0, 256, 3))
        if rng.random() < cfg.random_fill
        else (114,) * 3
    )
    out = cv2.warpAffine(
        image,
        A[:2],
        (size, size),
        flags=cv2.INTER_LINEAR if z > 0.8 else cv2.INTER_AREA,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=fill,
    )
    out = _photometric(out, cfg, rng)
    b = np.full_like(rows, np.nan)
    if has_box:
        b[found] = clip_boxes(transform_boxes(rows[found], A), (size, size))
    return out, b.reshape(np.shape(box))


def _photometric(img: np.ndarray, cfg: AugmentConfig, rng: np.random.Generator) -> np.ndarray:
    x = img.astype(np.float32)
    if cfg.color > 0:
        c = cfg.color
        if rng.random() < 0.8:
            hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV).astype(np.float32)
            hsv[..., 0] = (hsv[..., 0] + rng.uniform(-cfg.hue, cfg.hue)) % 180
            hsv[..., 1] *= rng.uniform(1 - c, 1 + c)
            x = cv2.cvtColor(np.clip(hsv, 0, 255).astype(np.uint8), cv2.COLOR_HSV2BGR).astype(
                np.float32
            )
        mean = x.mean()
        x = (x - mean) * rng.uniform(1 - c, 1 + c) + mean * rng.uniform(1 - c, 1 + c)
        x *= rng.uniform(1 - c / 3, 1 + c / 3, size=3).astype(np.float32)  # white balance
    if cfg.gray > 0 and rng.random() < cfg.gray:
        g = x.mean(-1, keepdims=True)
        x = np.repeat(g, 3, axis=-1)
    if cfg.blur > 0 and rng.random() < cfg.blur:
        x = cv2.GaussianBlur(x, (0, 0), rng.uniform(0.3, 1.5))
    if cfg.noise > 0:
        x += rng.normal(0, rng.uniform(0, cfg.noise), size=x.shape).astype(np.float32)
    return np.clip(x, 0, 255).astype(np.uint8)


def make_targets(
    boxes: np.ndarray, input_size: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """CenterNet targets for a batch with up to M boxes (animals) per image.

    Args:
        boxes: (B, 4) boxes in input pixels, NaN for images without an animal; or
            (B, M, 4), NaN rows for fewer animals.
        input_size: S (the output grid is S / 4).

    Returns:
        ``heat (B, 1, G, G)`` Gaussian peaks (1 at each centre cell, the largest where two
        overlap), ``index (B, M)`` flat centre cells, ``size (B, M, 2)`` log box sizes in
        cells, ``offset (B, M, 2)`` sub-cell centre offsets, ``mask (B, M)`` float 1 where
        a box is; for (B, 4) boxes without the M axis.
    """
    b = np.asarray(boxes, dtype=np.float64)
    single = b.ndim < 3
    b = b.reshape(len(b), -1, 4) if b.size else b.reshape(0, 1, 4)
    n, m = b.shape[:2]
    g = input_size // STRIDE
    heat = np.zeros((n, 1, g, g), np.float32)
    index = np.zeros((n, m), np.int64)
    size = np.zeros((n, m, 2), np.float32)
    offset = np.zeros((n, m, 2), np.float32)
    mask = np.zeros((n, m), np.float32)
    yy, xx = np.mgrid[0:g, 0:g]
    for i, j in np.ndindex(n, m):
        bx = b[i, j]
        if not np.isfinite(bx).all():
            continue
        w, h = bx[2] - bx[0], bx[3] - bx[1]
        if w < 1 or h < 1:
            continue
        gx = ((bx[0] + bx[2]) / 2 + 0.5) / STRIDE  # centre in grid units (cell corners at k)
        gy = ((bx[1] + bx[3]) / 2 + 0.5) / STRIDE
        cx, cy = int(np.clip(np.floor(gx), 0, g - 1)), int(np.clip(np.floor(gy), 0, g - 1))
        sigma = max(0.7, 0.12 * np.sqrt(w * h) / STRIDE)
        peak = np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sigma**2))
        heat[i, 0] = np.maximum(heat[i, 0], peak)
        index[i, j] = cy * g + cx
        size[i, j] = np.log([w / STRIDE, h / STRIDE])
        offset[i, j] = [gx - cx, gy - cy]
        mask[i, j] = 1.0
    if single:
        return heat, index[:, 0], size[:, 0], offset[:, 0], mask[:, 0]
    return heat, index, size, offset, mask
