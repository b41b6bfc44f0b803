"""The detector's training loss: CenterNet focal heat-map loss plus L1 size and offset terms."""

from __future__ import annotations

import numpy as np
import torch
from torch.nn import functional as F

from freipose.detect.augment import make_targets


def focal_loss(logits: torch.Tensor, target: torch.Tensor, n_pos: torch.Tensor) -> torch.Tensor:
    """CenterNet's penalty-reduced pixel-wise focal loss (alpha 2, beta 4)."""
    p = torch.sigmoid(logits).clamp(1e-4, 1 - 1e-4)
    pos = target.ge(0.999).float()
    pos_loss = -torch.log(p) * (1 - p) ** 2 * pos
    neg_loss = -torch.log(1 - p) * p**2 * (1 - target) ** 4 * (1 - pos)
    return (pos_loss.sum() + neg_loss.sum()) / n_pos.clamp(min=1.0)


def detection_loss(
    outputs: tuple[torch.Tensor, torch.Tensor, torch.Tensor], boxes: np.ndarray, input_size: int
) -> tuple[torch.Tensor, dict[str, float]]:
    """Focal heat-map loss + L1 on log size and offset at the centre cells.

    ``boxes`` (B, 4) or (B, M, 4) in input pixels, NaN where no animal
    (:func:`~freipose.detect.augment.make_targets`).
    """
    heat_l, size_p, off_p = outputs
    dev = heat_l.device
    given = np.asarray(boxes, dtype=np.float64)
    per_image = given[:, None] if given.ndim == 2 else given  # (B, M, 4), M = 1: one box
    heat, index, size, offset, mask = (
        torch.from_numpy(a).to(dev) for a in make_targets(per_image, input_size)
    )
    n_pos = mask.sum()
    l_heat = focal_loss(heat_l.float(), heat, n_pos)
    b, m_n = index.shape
    at = index.view(b, 1, m_n).expand(b, 2, m_n)
    sp = size_p.float().flatten(2).gather(2, at).transpose(1, 2)  # (B, M, 2)
    op = off_p.float().flatten(2).gather(2, at).transpose(1, 2)
    m = mask[..., None]
    denom = n_pos.clamp(min=1.0) * 2
    l_size = (F.l1_loss(sp, size, reduction="none") * m).sum() / denom
    l_off = (F.l1_loss(op, offset, reduction="none") * m).sum() / denom
    total = l_heat + l_size + l_off
    parts = {"heat": l_heat.item(), "size": l_size.item(), "offset": l_off.item()}
    return total, parts
