"""The single-class box detector: a MobileNetV2-style backbone with a CenterNet-style head.

Design (plain PyTorch, no pretrained weights needed):

* **Input**: the full frame, letterboxed (aspect kept, grey padding at the right/bottom)
  into a square of ``input_size`` pixels, RGB scaled to [-1, 1].
* **Backbone**: MobileNetV2 inverted residual blocks (expansion 6, depthwise 3x3, linear
  bottleneck) with a width multiplier, giving features at strides 4, 8 and 16.
* **Neck**: a light top-down feature pyramid back to stride 4.
* **Heads** at stride 4: a centre heat map (1 channel, sigmoid), the box size as
  ``log(w / 4), log(h / 4)`` (2 channels) and the sub-cell centre offset (2 channels).

One animal gives one Gaussian peak at its box centre; decoding takes the local maxima of
the heat map (3x3 max pooling), so several candidates per image come out naturally for the
multi-view consistency step.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from freipose.detect.base import DetectConfigError

STRIDE = 4


@dataclass(frozen=True)
class DetectorConfig:
    """Architecture and input settings (stored in the checkpoint).

    Attributes:
        input_size: side of the square network input in pixels (multiple of 32).
        width: channel width multiplier of the backbone (1.0 = MobileNetV2's channels).
        neck_channels: channels of the pyramid and the heads.
    """

    input_size: int = 256
    width: float = 0.5
    neck_channels: int = 48

    def __post_init__(self) -> None:
        if self.input_size < 64 or self.input_size % 32:
            raise DetectConfigError(
                f"input_size must be a multiple of 32 and >= 64, got {self.input_size}"
            )
        if not 0.1 <= self.width <= 2.0:
            raise DetectConfigError(f"width must be in [0.1, 2], got {self.width}")
        if self.neck_channels < 8:
            raise DetectConfigError(f"neck_channels must be >= 8, got {self.neck_channels}")

    def to_dict(self) -> dict:
        """The settings as a plain dict (stored in checkpoints)."""
        return asdict(self)


def _ch(c: float) -> int:
    """Round channels to a multiple of 8 (at least 8)."""
    return max(8, int(c + 4) // 8 * 8)


class ConvBN(nn.Sequential):
    """Convolution, batch norm and (with ``act``) ReLU6; "same" padding."""

    def __init__(
        self, cin: int, cout: int, k: int = 3, stride: int = 1, groups: int = 1, act: bool = True
    ):
        super().__init__(
            nn.Conv2d(cin, cout, k, stride, k // 2, groups=groups, bias=False),
            nn.BatchNorm2d(cout),
            nn.ReLU6(inplace=True) if act else nn.Identity(),
        )


class InvertedResidual(nn.Module):
    """MobileNetV2 block: 1x1 expand, 3x3 depthwise (stride), 1x1 linear projection."""

    def __init__(self, cin: int, cout: int, stride: int, expand: int):
        super().__init__()
        hidden = cin * expand
        layers: list[nn.Module] = []
        if expand != 1:
            layers.append(ConvBN(cin, hidden, 1))
        layers += [
            ConvBN(hidden, hidden, 3, stride, groups=hidden),
            ConvBN(hidden, cout, 1, act=False),
        ]
        self.block = nn.Sequential(*layers)
        self.residual = stride == 1 and cin == cout

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """The block's output (plus ``x`` when residual): (B, C, H, W) -> (B, C', H', W')."""
        y = self.block(x)
        return x + y if self.residual else y


class Backbone(nn.Module):
    """MobileNetV2-style feature extractor returning features at strides 4, 8 and 16."""

    # (expansion, channels, repeats, stride) per stage, as in MobileNetV2 up to stride 16.
    STAGES = ((1, 16, 1, 1), (6, 24, 2, 2), (6, 32, 3, 2), (6, 64, 3, 2), (6, 96, 2, 1))

    def __init__(self, width: float = 0.5):
        super().__init__()
        c0 = _ch(32 * width)
        self.stem = ConvBN(3, c0, 3, 2)
        blocks: list[nn.Module] = []
        cin = c0
        self.tap_index: list[int] = []
        self.channels: list[int] = []
        for si, (t, c, n, s) in enumerate(self.STAGES):
            cout = _ch(c * width)
            for i in range(n):
                blocks.append(InvertedResidual(cin, cout, s if i == 0 else 1, t))
                cin = cout
            if si in (1, 2, 4):  # strides 4, 8, 16
                self.tap_index.append(len(blocks) - 1)
                self.channels.append(cout)
        self.blocks = nn.ModuleList(blocks)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The feature maps at the tapped blocks (strides 4, 8, 16) of images (B, 3, H, W)."""
        x = self.stem(x)
        feats = []
        for i, b in enumerate(self.blocks):
            x = b(x)
            if i in self.tap_index:
                feats.append(x)
        return feats


class DetectorNet(nn.Module):
    """Backbone + top-down pyramid + centre/size/offset heads at stride 4.

    ``forward(x (B, 3, S, S))`` returns ``(heat_logits (B, 1, S/4, S/4), size (B, 2, S/4,
    S/4), offset (B, 2, S/4, S/4))``.
    """

    def __init__(self, config: DetectorConfig):
        super().__init__()
        self.config = config
        self.backbone = Backbone(config.width)
        n = config.neck_channels
        self.lateral = nn.ModuleList([ConvBN(c, n, 1) for c in self.backbone.channels])
        self.smooth = nn.ModuleList(
            [nn.Sequential(ConvBN(n, n, 3, groups=n), ConvBN(n, n, 1)) for _ in range(2)]
        )

        def head(cout: int) -> nn.Sequential:
            return nn.Sequential(ConvBN(n, n, 3, groups=n), ConvBN(n, n, 1), nn.Conv2d(n, cout, 1))

        self.heat = head(1)
        self.size = head(2)
        self.offset = head(2)
        # Start with a low foreground probability (CenterNet's bias prior).
        nn.init.constant_(self.heat[-1].bias, -math.log((1 - 0.01) / 0.01))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Heat map logits (B, 1, H/4, W/4), sizes (B, 2, H/4, W/4), offsets (B, 2, H/4, W/4)."""
        f4, f8, f16 = self.backbone(x)
        p = self.lateral[2](f16)
        p = self.smooth[0](self.lateral[1](f8) + F.interpolate(p, scale_factor=2.0, mode="nearest"))
        p = self.smooth[1](self.lateral[0](f4) + F.interpolate(p, scale_factor=2.0, mode="nearest"))
        return self.heat(p), self.size(p), self.offset(p)


def letterbox_affine(size: tuple[int, int], input_size: int) -> np.ndarray:
    """The 3x3 map from full-image pixels (``size`` = (w, h)) to the letterboxed input.

    The image is scaled by ``input_size / max(w, h)`` and placed at the top-left corner;
    pixel centres map as ``u' = (u + 0.5) * s - 0.5``.
    """
    w, h = size
    s = input_size / max(w, h)
    return np.array([[s, 0.0, 0.5 * s - 0.5], [0.0, s, 0.5 * s - 0.5], [0.0, 0.0, 1.0]])


def to_tensor(images: list[np.ndarray] | np.ndarray) -> torch.Tensor:
    """BGR uint8 images (B, S, S, 3) -> float tensor (B, 3, S, S) RGB in [-1, 1]."""
    arr = np.ascontiguousarray(np.asarray(images)[..., ::-1])
    t = torch.from_numpy(arr).permute(0, 3, 1, 2).float()
    return t / 127.5 - 1.0


@torch.no_grad()
def decode(
    heat_logits: torch.Tensor,
    size: torch.Tensor,
    offset: torch.Tensor,
    top_k: int = 5,
    min_score: float = 0.05,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Peaks of the heat map as boxes in network-input pixels.

    Returns one ``(boxes (k, 4), scores (k,))`` per image, best first (k <= top_k).
    """
    heat = torch.sigmoid(heat_logits.float())
    peak = F.max_pool2d(heat, 3, 1, 1)
    heat = torch.where(peak == heat, heat, torch.zeros_like(heat))
    b, _, h, w = heat.shape
    k = min(top_k, h * w)
    scores, idx = heat.view(b, -1).topk(k, dim=1)
    ys = torch.div(idx, w, rounding_mode="floor")
    xs = idx % w
    out = []
    for i in range(b):
        keep = scores[i] >= min_score
        yi, xi, si = ys[i][keep], xs[i][keep], scores[i][keep]
        off = offset[i, :, yi, xi].float()  # (2, k)
        sz = torch.exp(size[i, :, yi, xi].float().clamp(-10, 10)) * STRIDE  # (2, k)
        # Cell (x, y) covers input pixels [4x - 0.5, 4x + 3.5): its corner is 4x - 0.5.
        cx = (xi.float() + off[0]) * STRIDE - 0.5
        cy = (yi.float() + off[1]) * STRIDE - 0.5
        boxes = torch.stack([cx - sz[0] / 2, cy - sz[1] / 2, cx + sz[0] / 2, cy + sz[1] / 2], 1)
        out.append((boxes.cpu().numpy().astype(np.float64), si.cpu().numpy().astype(np.float64)))
    return out
