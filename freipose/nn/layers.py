"""Building blocks of the voxel network.

The 2D encoder, 3D U-Net, soft-argmax, 2D heads (refinement and baseline), heat maps and
confidence-weighted triangulation; the unprojection is in :mod:`freipose.nn.unprojection`
(:func:`unproject` is importable from here too).

Shapes: B samples, V views, K keypoints, C channels, G voxels per cube edge, S crop size,
h = w = S / stride feature size. Crop pixel coordinates use the project convention (pixel
centres at integers); a feature pixel ``j`` covers crop pixels ``[j*s, (j+1)*s)``, so its
centre is at ``(j + 0.5) * s - 0.5``, which is ``grid_sample``'s ``align_corners=False``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from freipose.nn.geometry import (
    normalized_ray_distances,
    pixels_to_normalized,
    voxel_axis,
)
from freipose.nn.unprojection import unproject as unproject  # re-exported: the layers' API


def norm_layer(kind: str, channels: int, dims: int = 2) -> nn.Module:
    """A normalization layer: ``group`` (GroupNorm, up to 8 groups), ``batch`` or ``none``."""
    if kind == "group":
        groups = next(g for g in (8, 4, 2, 1) if channels % g == 0)
        return nn.GroupNorm(groups, channels)
    if kind == "batch":
        return nn.BatchNorm2d(channels) if dims == 2 else nn.BatchNorm3d(channels)
    return nn.Identity()


def conv2d(cin: int, cout: int, k: int, norm: str, act: str = "relu") -> nn.Sequential:
    """Conv (same padding) + norm + activation."""
    layers: list[nn.Module] = [nn.Conv2d(cin, cout, k, padding=k // 2, bias=norm == "none")]
    layers.append(norm_layer(norm, cout, 2))
    layers.append(nn.ReLU(inplace=True) if act == "relu" else nn.LeakyReLU(0.1, inplace=True))
    return nn.Sequential(*layers)


class Conv3d(nn.Conv3d):
    """``nn.Conv3d`` whose 1x1x1 kernels run as one matrix product on channels-last volumes.

    A 1x1x1 convolution of a channels-last (B, C, D, H, W) volume is ``linear`` on its
    (B, D, H, W, C) view; the output is channels-last too. PyTorch's CPU convolution takes
    its reference kernel for small batches of 1x1x1 kernels on one thread and copies
    channels-last volumes in and out of it. Other kernels and layouts are ``nn.Conv3d``.
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """The convolution of a (B, C, D, H, W) volume."""
        pointwise = self.kernel_size == (1, 1, 1) and self.stride == (1, 1, 1)
        if not (pointwise and self.groups == 1 and x.dim() == 5):
            return super().forward(x)
        if not x.is_contiguous(memory_format=torch.channels_last_3d) or x.is_contiguous():
            return super().forward(x)
        y = F.linear(x.permute(0, 2, 3, 4, 1), self.weight.flatten(1).to(x.dtype), self.bias)
        return y.permute(0, 4, 1, 2, 3)


def conv3d(cin: int, cout: int, k: int, norm: str, stride: int = 1) -> nn.Sequential:
    """3D conv (same padding) + norm + ReLU."""
    return nn.Sequential(
        Conv3d(cin, cout, k, stride=stride, padding=k // 2, bias=norm == "none"),
        norm_layer(norm, cout, 3),
        nn.ReLU(inplace=True),
    )


class Encoder2D(nn.Module):
    """VGG-style 2D encoder shared by all views.

    Input (N, 3, S, S) (BGR / 255 - 0.5). Returns the features (N, feature_channels, S/s,
    S/s) and the skip maps taken before each max-pool, coarsest first: ``skips[j]`` is
    (N, encoder_channels[pools-1-j], 2**(j+1) S/s, 2**(j+1) S/s), i.e. at stride s / 2**(j+1)
    (``skip_channels`` lists their channels in that order).
    """

    def __init__(
        self,
        channels: tuple[int, ...],
        convs: tuple[int, ...],
        pools: int,
        out_channels: int,
        norm: str,
    ):
        super().__init__()
        self.pools = pools
        blocks = []
        cin = 3
        for c, n in zip(channels, convs):
            layers = []
            for _ in range(n):
                layers.append(conv2d(cin, c, 3, norm))
                cin = c
            blocks.append(nn.Sequential(*layers))
        self.blocks = nn.ModuleList(blocks)
        self.out = conv2d(cin, out_channels, 3, norm)
        self.skip_channels = tuple(channels[pools - 1 - j] for j in range(pools))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Features and skip maps of (N, 3, S, S) crops (see the class docstring)."""
        skips: list[torch.Tensor] = []
        for i, block in enumerate(self.blocks):
            x = block(x)
            if i < self.pools:
                skips.insert(0, x)
                x = F.max_pool2d(x, 2)
        return self.out(x), skips


class UNet3D(nn.Module):
    """Encoder-decoder 3D CNN on the fused feature volume, one score volume per keypoint.

    Each encoder level is a 1x1x1 conv then a stride-2 3x3x3 conv; each decoder level a
    stride-2 transposed conv, concatenation with the (1x1x1-reduced) skip and a 3x3x3 conv.
    The full-resolution output adds a 1x1x1 projection of the input volume. Returns the list
    of score volumes (B, K, G, G, G): the deep-supervision ones (coarse levels, upsampled
    trilinearly) first, the final one last. In eval mode only the final one: the
    deep-supervision volumes serve the training loss alone.
    """

    def __init__(self, cin: int, channels: tuple[int, ...], out: int, norm: str, deep: bool):
        super().__init__()
        self.deep = deep
        downs = []
        c_prev = cin
        for c in channels:
            downs.append(nn.Sequential(conv3d(c_prev, c, 1, norm), conv3d(c, c, 3, norm, stride=2)))
            c_prev = c
        self.downs = nn.ModuleList(downs)
        self.bottleneck = conv3d(c_prev, c_prev, 1, norm)
        ups, skips, fuses, heads = [], [], [], []
        for lvl in range(len(channels) - 2, -1, -1):
            c = channels[lvl]
            ups.append(nn.ConvTranspose3d(c_prev, c, 4, stride=2, padding=1))
            skips.append(conv3d(channels[lvl], c, 1, norm))
            fuses.append(conv3d(2 * c, c, 3, norm))
            heads.append(Conv3d(c, out, 1, bias=False))  # softmax ignores a bias
            c_prev = c
        self.ups, self.skips, self.fuses = (
            nn.ModuleList(ups),
            nn.ModuleList(skips),
            nn.ModuleList(fuses),
        )
        self.heads = nn.ModuleList(heads)
        self.bottleneck_head = Conv3d(channels[-1], out, 1, bias=False)
        c0 = channels[0]
        self.final_up = nn.ConvTranspose3d(c_prev, c0, 4, stride=2, padding=1)
        self.final_in = Conv3d(cin, c0, 1)
        self.final = Conv3d(c0, out, 1, bias=False)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Score volumes of a (B, C, G, G, G) feature volume (see the class docstring)."""
        size = x.shape[-3:]
        deep = self.deep and self.training
        inp = x
        acts = []
        for down in self.downs:
            x = down(x)
            acts.append(x)
        x = self.bottleneck(x)
        outs = []
        if deep:
            outs.append(self.bottleneck_head(x))
        for i, (up, skip, fuse) in enumerate(zip(self.ups, self.skips, self.fuses)):
            lvl = len(self.downs) - 2 - i
            x = fuse(torch.cat([F.relu(up(x)), skip(acts[lvl])], dim=1))
            if deep:
                outs.append(self.heads[i](x))
        x = F.relu(self.final_up(x) + self.final_in(inp))
        outs = [F.interpolate(o, size=size, mode="trilinear", align_corners=False) for o in outs]
        outs.append(self.final(x))
        return outs


def peak_window(probs: torch.Tensor, shape: tuple[int, ...], radius: int) -> torch.Tensor:
    """Distributions kept within ``radius`` cells (per axis) of their largest cell, renormalised.

    Soft-argmax is the mean of the whole distribution, so a second mode (the left ear's map
    lighting up at the right ear too) pulls it toward the midpoint of the two; restricted to a
    window around the peak it is the position of the main mode alone. The 2D maps use it
    (:func:`softargmax2d`); the 3D volumes are decoded whole (docs/models.md, "Decoding").

    Args:
        probs: (N, K, prod(shape)) distributions over a grid of ``shape`` (row-major).
        shape: the grid's shape, e.g. (G, G, G) or (h, w).
        radius: half-width of the window in cells; 0 or less returns ``probs`` unchanged.

    Returns:
        (N, K, prod(shape)) distributions, zero outside the windows.
    """
    if radius <= 0:
        return probs
    N, K = probs.shape[:2]
    peak = probs.argmax(-1)  # (N, K)
    # the window is a product of one interval per axis: build it from (N, K, size) masks
    keep = torch.ones((N, K) + (1,) * len(shape), dtype=probs.dtype, device=probs.device)
    stride = 1
    for axis in range(len(shape) - 1, -1, -1):
        size = shape[axis]
        cell = torch.arange(size, device=probs.device)
        centre = peak // stride % size
        inside = ((cell - centre[..., None]).abs() <= radius).to(probs.dtype)  # (N, K, size)
        view = [N, K] + [1] * len(shape)
        view[2 + axis] = size
        keep = keep * inside.reshape(view)
        stride *= size
    kept = probs * keep.reshape(N, K, -1)
    return kept / kept.sum(-1, keepdim=True).clamp_min(1e-12)


def softargmax3d(
    logits: torch.Tensor,
    center: torch.Tensor,
    cube_size: float,
    rotation: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Decode score volumes to world points by soft-argmax.

    Args:
        logits: (B, K, G, G, G) scores; axes are the x, y, z voxel indices.
        center: (B, 3) cube centres in mm.
        cube_size: distance between the outermost voxel centres (mm).
        rotation: optional (B, 3, 3) orientation of the grid axes in the world (voxel
            offset ``o`` sits at ``center + rotation @ o``); identity when None.

    Returns:
        ``(points, probs)``: (B, K, 3) expected world positions (float32) and the
        (B, K, G**3) softmax distributions.
    """
    B, K = logits.shape[:2]
    G = logits.shape[-1]
    # contiguous first: a channels-last volume would make the softmax run along a stride
    probs = torch.softmax(logits.float().contiguous().reshape(B, K, -1), dim=-1)
    # the expectation of a lattice offset is the expectation of each axis's marginal
    ax = voxel_axis(G, cube_size, device=logits.device)  # (G,)
    p = probs.reshape(B, K, G, G, G)
    yz = p.sum(2)  # (B, K, G, G) marginal of the y and z indices
    local = torch.stack([p.sum((3, 4)) @ ax, yz.sum(3) @ ax, yz.sum(2) @ ax], -1)  # (B, K, 3)
    if rotation is not None:
        local = local @ rotation.float().transpose(1, 2)
    return center.float()[:, None, :] + local, probs


def volume_confidence(probs: torch.Tensor, grid_size: int) -> torch.Tensor:
    """Peak mass of soft-argmax distributions: the largest probability in any 3x3x3 block.

    The block sums are separable (three 3-cell sums, one per axis, zero outside the grid).
    No gradient flows through the result: it reports how sharp a volume is, no loss uses it.

    Args:
        probs: (B, K, G**3) distributions.
        grid_size: G, voxels per cube edge.

    Returns:
        (B, K) in [0, 1]; near 1 for a sharp, unimodal score volume.
    """
    B, K = probs.shape[:2]
    G = grid_size
    mass = probs.detach().reshape(B * K, G, G, G)
    for dim in (1, 2, 3):
        total = mass.clone()
        total.narrow(dim, 1, G - 1).add_(mass.narrow(dim, 0, G - 1))
        total.narrow(dim, 0, G - 1).add_(mass.narrow(dim, 1, G - 1))
        mass = total
    return mass.reshape(B, K, -1).amax(-1).clamp(0.0, 1.0)


def softargmax2d(
    logits: torch.Tensor, stride: float, window: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    """Soft-argmax of 2D maps at ``stride`` crop pixels per map pixel.

    Args:
        logits: (N, K, h, w).
        stride: crop pixels per map pixel.
        window: when positive, the mean is taken within this many map pixels of each
            map's peak (:func:`peak_window`); 0 takes the whole map.

    Returns:
        ``(uv, probs)``: (N, K, 2) crop pixels (x, y) and (N, K, h*w) distributions (of the
        whole map).
    """
    N, K, h, w = logits.shape
    probs = torch.softmax(logits.float().reshape(N, K, -1), dim=-1)
    ys = (torch.arange(h, device=logits.device, dtype=torch.float32) + 0.5) * stride - 0.5
    xs = (torch.arange(w, device=logits.device, dtype=torch.float32) + 0.5) * stride - 0.5
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    coords = torch.stack([gx.reshape(-1), gy.reshape(-1)], dim=-1)  # (h*w, 2)
    return peak_window(probs, (h, w), window) @ coords, probs


def gaussian_heatmaps(uv: torch.Tensor, size: int, stride: float, sigma: float) -> torch.Tensor:
    """Gaussian heat maps at feature resolution around crop-pixel points.

    Args:
        uv: (N, K, 2) crop pixels.
        size: h = w of the maps.
        stride: crop pixels per map pixel.
        sigma: the Gaussians' width in map pixels.

    Returns:
        (N, K, size, size) in [0, 1].
    """
    f = (uv.float() + 0.5) / stride - 0.5
    ax = torch.arange(size, device=uv.device, dtype=torch.float32)
    dx = (ax[None, None, :] - f[..., 0:1]) ** 2  # (N, K, w)
    dy = (ax[None, None, :] - f[..., 1:2]) ** 2  # (N, K, h)
    return torch.exp(-(dy[..., :, None] + dx[..., None, :]) / (2 * sigma**2))


def gaussian_log_prior(uv: torch.Tensor, size: int, stride: float, sigma: float) -> torch.Tensor:
    """Log of an unnormalised Gaussian, ``-d^2 / (2 sigma^2)`` (map px), around crop points.

    Args:
        uv: (N, K, 2) crop pixels.
        size: side of the maps.
        stride: crop pixels per map pixel.
        sigma: the Gaussians' width in map pixels.

    Returns:
        (N, K, size, size) float32.
    """
    f = (uv.float() + 0.5) / stride - 0.5
    ax = torch.arange(size, device=uv.device, dtype=torch.float32)
    dx = (ax[None, None, :] - f[..., 0:1]) ** 2
    dy = (ax[None, None, :] - f[..., 1:2]) ** 2
    return -(dy[..., :, None] + dx[..., None, :]) / (2 * sigma**2)


def _skip_decoder(
    c_in: int, channels: list[int], skip_ch: tuple[int, ...], norm: str
) -> tuple[nn.ModuleList, nn.ModuleList, nn.ModuleList]:
    """Layers of ``len(channels)`` decoder steps (:func:`_skip_decode`).

    Stride-2 transposed convs, 1x1 convs of the encoder's skip maps, 3x3 fusing convs; step
    ``i`` has ``channels[i]`` channels and takes ``skip_ch[i]`` skip channels.
    """
    ups, skips, fuses = [], [], []
    c_prev = c_in
    for c, cs in zip(channels, skip_ch):
        ups.append(nn.ConvTranspose2d(c_prev, c, 4, stride=2, padding=1))
        skips.append(conv2d(cs, c, 1, norm, "lrelu"))
        fuses.append(conv2d(2 * c, c, 3, norm, "lrelu"))
        c_prev = c
    return nn.ModuleList(ups), nn.ModuleList(skips), nn.ModuleList(fuses)


def _skip_decode(
    x: torch.Tensor,
    ups: nn.ModuleList,
    skips: nn.ModuleList,
    fuses: nn.ModuleList,
    skip_maps: list[torch.Tensor],
) -> torch.Tensor:
    """Each step doubles the resolution of ``x`` and fuses the skip map of that scale."""
    for up, skip, fuse, s in zip(ups, skips, fuses, skip_maps):
        x = fuse(torch.cat([F.leaky_relu(up(x), 0.1), skip(s)], dim=1))
    return x


class Head2D(nn.Module):
    """Per-view 2D keypoint head: maps ``levels`` octaves finer than the features, confidences.

    Used as the refinement head (input: features + P0 heat maps) and as the baseline's 2D
    detector (features only). A base of three convolutions at feature resolution, then
    ``levels`` decoder steps (stride-2 transposed conv, concatenation with the encoder's skip
    map of that resolution, 3x3 conv; channels halve at each step, as in the original's
    RefineNet2D). Outputs map logits (N, K, 2**levels h, 2**levels w) and confidence logits of
    the same shape (the per-keypoint confidence is their expectation under the map's softmax).
    """

    def __init__(
        self,
        feat_ch: int,
        skip_ch: tuple[int, ...],
        k: int,
        ch: int,
        norm: str,
        heat_in: int,
        levels: int = 1,
    ):
        super().__init__()
        if not 1 <= levels <= len(skip_ch):
            raise ValueError(f"Head2D: levels must be in 1..{len(skip_ch)}, got {levels}")
        self.base = nn.Sequential(
            conv2d(feat_ch + heat_in, ch, 1, norm, "lrelu"),
            conv2d(ch, ch, 3, norm, "lrelu"),
            conv2d(ch, ch, 3, norm, "lrelu"),
        )
        channels = [max(ch // 2 ** (lvl + 1), 4) for lvl in range(levels)]
        self.ups, self.skips, self.fuses = _skip_decoder(ch, channels, skip_ch, norm)
        self.maps = nn.Conv2d(channels[-1], k, 1, bias=False)
        self.conf = nn.Conv2d(channels[-1], k, 1)

    def forward(
        self, feat: torch.Tensor, skips: list[torch.Tensor], heat: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Map and confidence logits of features, skip maps and optional heat maps."""
        x = feat if heat is None else torch.cat([feat, heat.to(feat.dtype)], dim=1)
        x = _skip_decode(self.base(x), self.ups, self.skips, self.fuses, skips)
        return self.maps(x), self.conf(x)


class FeatureDecoder(nn.Module):
    """Raises the encoder's features ``levels`` octaves with its skip maps (U-Net style).

    Each step: stride-2 transposed conv, concatenation with the (1x1-reduced) skip map of
    that resolution, 3x3 conv; the channels stay ``ch``. Input (N, ch, h, w) features and the
    encoder's skips (coarsest first); output (N, ch, 2**levels h, 2**levels w).
    """

    def __init__(self, ch: int, skip_ch: tuple[int, ...], norm: str, levels: int):
        super().__init__()
        if not 1 <= levels <= len(skip_ch):
            raise ValueError(f"FeatureDecoder: levels must be in 1..{len(skip_ch)}, got {levels}")
        self.ups, self.skips, self.fuses = _skip_decoder(ch, [ch] * levels, skip_ch, norm)

    def forward(self, feat: torch.Tensor, skips: list[torch.Tensor]) -> torch.Tensor:
        """The raised features (see the class docstring)."""
        return _skip_decode(feat, self.ups, self.skips, self.fuses, skips)


def decode_head(
    maps: torch.Tensor, conf_logits: torch.Tensor, stride: float, window: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    """2D points (N, K, 2) crop px and confidences (N, K) in (0, 1) from :class:`Head2D`.

    ``window`` (map pixels) restricts the soft-argmax to each map's peak
    (:func:`softargmax2d`); the confidence always reads the whole map.
    """
    uv, probs = softargmax2d(maps, stride, window)
    c = (probs * conf_logits.float().flatten(2)).sum(-1)
    return uv, torch.sigmoid(c)


def triangulate_with_prior(
    uv: torch.Tensor,
    weights: torch.Tensor,
    K: torch.Tensor,
    R: torch.Tensor,
    t: torch.Tensor,
    dist: torch.Tensor | None,
    prior: torch.Tensor,
    prior_weight: float | torch.Tensor = 1e-3,
) -> torch.Tensor:
    """Confidence-weighted linear triangulation of crop pixels, anchored to a prior point.

    Minimises ``sum_v w_v |r_v(X)|^2 + prior_weight |X - prior|^2`` where ``r_v`` is the
    DLT residual (the lateral distance in mm from view v's ray, at the point's depth). With
    two or more confident views the prior is negligible; with one view the result is the
    point of that view's ray nearest the prior (the depth-preserving fusion of the method,
    eq. 5.3); with none it is the prior.

    Args:
        uv: (B, V, K, 2) distorted crop pixels.
        K: (B, V, 3, 3) affine crop intrinsics.
        R: (B, V, 3, 3) camera rotations.
        t: (B, V, 3) camera translations (mm).
        dist: (B, V, 5) distortion coefficients (or None).
        weights: (B, V, K) non-negative confidences (0 for padding views).
        prior: (B, K, 3) world mm.
        prior_weight: scalar or (B, K) weight of the prior (same units as ``weights``).

    Returns:
        (B, K, 3) world mm.
    """
    xy = pixels_to_normalized(uv.float(), K.float(), None if dist is None else dist.float())
    return triangulate_normalized(xy, weights, R, t, prior, prior_weight)


def triangulate_normalized(
    xy: torch.Tensor,
    weights: torch.Tensor,
    R: torch.Tensor,
    t: torch.Tensor,
    prior: torch.Tensor,
    prior_weight: float | torch.Tensor = 1e-3,
) -> torch.Tensor:
    """:func:`triangulate_with_prior` of undistorted normalized coordinates.

    Args:
        xy: (B, V, K, 2) float32 from :func:`freipose.nn.geometry.pixels_to_normalized`.
        weights: (B, V, K) non-negative confidences (0 for padding views).
        R: (B, V, 3, 3) camera rotations.
        t: (B, V, 3) camera translations (mm).
        prior: (B, K, 3) world mm.
        prior_weight: scalar or (B, K) weight of the prior.

    Returns:
        (B, K, 3) world mm.
    """
    x, y = xy[..., 0], xy[..., 1]  # (B, V, K)
    Rt = torch.cat([R, t[..., None]], dim=-1).float()  # (B, V, 3, 4)
    r1 = x[..., None] * Rt[:, :, None, 2] - Rt[:, :, None, 0]  # (B, V, K, 4)
    r2 = y[..., None] * Rt[:, :, None, 2] - Rt[:, :, None, 1]
    rows = torch.stack([r1, r2], dim=1)  # (B, 2, V, K, 4)
    w = weights.float().clamp_min(0)[:, None, :, :, None]
    A, b = rows[..., :3], -rows[..., 3:]
    AtA = (A[..., :, None] * A[..., None, :] * w[..., None]).sum(dim=(1, 2))  # (B, K, 3, 3)
    Atb = (A * b * w).sum(dim=(1, 2))  # (B, K, 3)
    eye = torch.eye(3, dtype=AtA.dtype, device=AtA.device)
    pw = torch.as_tensor(prior_weight, dtype=AtA.dtype, device=AtA.device)
    pw = pw.expand(AtA.shape[:-2])
    AtA = AtA + pw[..., None, None] * eye
    Atb = Atb + pw[..., None] * prior.float()
    return torch.linalg.solve(AtA, Atb[..., None])[..., 0]


def refuse_outlier_views(
    P1: torch.Tensor,
    uv: torch.Tensor,
    conf: torch.Tensor,
    cameras: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None],
    prior: torch.Tensor,
    prior_scale: torch.Tensor,
    max_distance: float,
    rounds: int = 2,
    xy: torch.Tensor | None = None,
) -> torch.Tensor:
    """The fusion of :func:`triangulate_with_prior` again, without the views that disagree.

    A view whose 2D point lies more than ``max_distance`` mm from the fused point ``P1``
    (its distance from the view's ray at the point's depth, :func:`ray_distances`) is left
    out, so that one view that refined onto the wrong body part does not pull the point;
    a keypoint that no view supports falls back to the prior. Each further round measures
    the distances from the last point (a good view that the wrong one had pulled the first
    fusion away from comes back).

    Args:
        P1: (B, K, 3) the fusion of every view, world mm.
        uv: (B, V, K, 2) crop pixels of the views.
        conf: (B, V, K) their confidences (0 for padding views).
        cameras: ``(K (B, V, 3, 3), R (B, V, 3, 3), t (B, V, 3), dist (B, V, 5) or None)``.
        prior: (B, K, 3) the prior point (P0), world mm.
        prior_scale: (1 or B, K) the prior's weight per unit of the views' confidence.
        max_distance: mm.
        rounds: fusions after the first.
        xy: ``uv`` in undistorted normalized coordinates
            (:func:`freipose.nn.geometry.pixels_to_normalized`), when the caller has them.

    Returns:
        (B, K, 3) world mm.
    """
    Kc, R, t, dist = cameras
    # the views' rays do not change between the rounds: undistort once
    if xy is None:
        xy = pixels_to_normalized(uv.float(), Kc.float(), None if dist is None else dist.float())
    for _ in range(rounds):
        kept = conf * (normalized_ray_distances(P1, xy, R, t) <= max_distance)
        P1 = triangulate_normalized(xy, kept, R, t, prior, prior_scale * kept.sum(1) + 1e-3)
    return P1
