"""Exact keypoint visibility: inside the image and not hidden by a body part, wall or floor."""

from __future__ import annotations

import numpy as np

from freipose.geometry import CameraRig, project
from freipose.synth.body import KEYPOINT_OWNERS, PART_NAMES, BodyGeometry
from freipose.synth.rig import ArenaConfig


def _owner_mask(n_kp: int, n_parts: int) -> np.ndarray:
    """(K, N) the parts each keypoint belongs to.

    Several animals (``freipose.synth.social``): keypoint ``k`` belongs to animal
    ``k // 12``, whose parts are ``a * len(PART_NAMES) ...``.
    """
    own = np.zeros((n_kp, n_parts), bool)
    per = len(KEYPOINT_OWNERS)
    for k in range(n_kp):
        a, j = divmod(k, per) if n_parts > len(PART_NAMES) else (0, k)
        if j < per:
            own[k, [i + a * len(PART_NAMES) for i in KEYPOINT_OWNERS[j]]] = True
    return own


def _other_animal_mask(n_kp: int, n_parts: int) -> np.ndarray:
    """(K, N) the parts of the animals other than each keypoint's (all False for one)."""
    per, n = len(KEYPOINT_OWNERS), len(PART_NAMES)
    if n_parts <= n:
        return np.zeros((n_kp, n_parts), bool)
    return (np.arange(n_kp)[:, None] // per) != (np.arange(n_parts)[None, :] // n)


def keypoint_visibility(
    geom: BodyGeometry,
    rig: CameraRig,
    arena: ArenaConfig | None,
    tolerance_mm: float = 1.5,
    chunk: int = 256,
    hidden_by_other: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Project the keypoints and decide their visibility in every view.

    A keypoint is visible in a view when its projection is inside the image and the segment
    from the camera centre to the keypoint enters no body part (other than the parts the
    keypoint belongs to, see ``KEYPOINT_OWNERS``), wall or floor more than ``tolerance_mm``
    before the keypoint. This is the analytic form of a z-buffer test along the keypoint's
    own viewing ray.

    A geometry of several animals (``freipose.synth.social``: parts and keypoints one
    animal after the other) tests every keypoint against every animal's parts.

    Args:
        geom: the body (or bodies) over T frames.
        rig: the C cameras.
        arena: the walls (None: no walls).
        tolerance_mm: how far before the keypoint a hit must be to hide it.
        chunk: frames per vectorized batch.
        hidden_by_other: (T, C, K) bool, filled when given: the keypoint is hidden by
            another animal's body.

    Returns:
        ``(points2d (T, C, K, 2), visible (T, C, K) bool)``; points2d are the exact
        (distorted) projections of every keypoint, whether visible or not.
    """
    kp = geom.keypoints
    T, K, _ = kp.shape
    N = geom.centers.shape[1]
    own = _owner_mask(K, N)
    other = _other_animal_mask(K, N)
    pts2d = np.stack([project(kp, cam) for cam in rig], axis=1)
    vis = np.zeros((T, len(rig), K), bool)
    for ci, cam in enumerate(rig):
        o = cam.center
        w, h = cam.size
        uv = pts2d[:, ci]
        inside = np.all(np.isfinite(uv), -1) & (uv[..., 0] >= -0.5) & (uv[..., 0] <= w - 0.5)
        inside &= (uv[..., 1] >= -0.5) & (uv[..., 1] <= h - 0.5)
        for t0 in range(0, T, chunk):
            sl = slice(t0, min(T, t0 + chunk))
            X = kp[sl]  # (t, K, 3)
            d = X - o
            dist = np.linalg.norm(d, axis=-1)  # (t, K)
            u = d / dist[..., None]
            M = geom.axes[sl] / geom.radii[sl][:, :, None, :]  # (t, N, 3, 3): dir @ M -> unit frame
            op = np.einsum("tni,tnij->tnj", o - geom.centers[sl], M)  # (t, N, 3)
            dp = np.einsum("tki,tnij->tknj", u, M)  # (t, K, N, 3)
            a = np.sum(dp * dp, -1)
            b = np.sum(dp * op[:, None], -1)
            c = np.sum(op * op, -1)[:, None] - 1.0
            disc = b * b - a * c
            sq = np.sqrt(np.maximum(disc, 0))
            s1 = (-b - sq) / a
            s2 = (-b + sq) / a
            blocked = (disc > 0) & (s2 > 0) & (s1 < dist[..., None] - tolerance_mm) & ~own[None]
            occluded = blocked.any(-1) | (X[..., 2] < 0)
            if hidden_by_other is not None:
                hidden_by_other[sl, ci] = inside[sl] & (blocked & other[None]).any(-1)
            if arena is not None and arena.wall_height > 0:
                occluded |= _wall_hits(o, u, dist - tolerance_mm, arena)
            vis[sl, ci] = inside[sl] & ~occluded
    return pts2d, vis


def _wall_hits(o: np.ndarray, u: np.ndarray, max_s: np.ndarray, arena: ArenaConfig) -> np.ndarray:
    """Whether rays ``o + s u`` (u (..., 3)) cross an arena wall at 0 < s < max_s."""
    hx, hy = arena.half
    hit = np.zeros(u.shape[:-1], bool)
    for axis, val in ((0, hx), (0, -hx), (1, hy), (1, -hy)):
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (val - o[axis]) / u[..., axis]
        p = o + np.nan_to_num(s)[..., None] * u
        other = 1 - axis
        lim = hy if axis == 0 else hx
        on_wall = (
            (np.abs(p[..., other]) <= lim) & (p[..., 2] >= 0) & (p[..., 2] <= arena.wall_height)
        )
        hit |= (s > 0) & (s < max_s) & on_wall
    return hit
