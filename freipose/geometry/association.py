"""Cross-view association: which 2D detections of several animals belong to the same animal.

Every view sees some of the animals as points (box centres, or one keypoint), with false
points among them and animals missing where they are hidden. :func:`associate` groups the
points of all views into 3D hypotheses, at most one point per view each:

1. **proposals**: every pair of views and every pair of their points is triangulated
   (:func:`freipose.geometry.triangulate`); a pair is kept when the 3D point lies in front of
   both cameras, projects back onto both points within their tolerances (the epipolar
   consistency of the pair), and lies inside ``bounds`` when given;
2. **verification**: a proposal's projection into every other view is matched to the
   nearest point of that view within the point's tolerance; with ``sizes`` (the boxes'
   sizes in pixels) a view also agrees only when the animal's size in mm seen from it
   (``size * depth / focal``) is within ``max_size_ratio`` of the size seen from the pair;
3. **greedy selection**: the proposal with the most agreeing views wins (ties: the smaller
   mean error relative to the tolerances); it is re-triangulated from its points
   (weighted DLT), verified once more, and its points are taken out; the remaining
   proposals are verified again on the points left, until no proposal reaches
   ``min_views`` (or ``max_hypotheses`` are found). Points that join no hypothesis are
   left over (false detections, or an animal seen by fewer than ``min_views`` views).

A ghost (animal A in one view triangulated with animal B in another) projects onto
nothing in the other views, so with three or more views the true animals win the
greedy order; ``min_views = 3`` rejects ghosts and pairs of false points outright where
every animal is seen by three views.

Shapes: C cameras; view ``c`` has ``n_c`` points; H hypotheses.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from freipose.geometry.camera import CameraRig
from freipose.geometry.projection import project_rig
from freipose.geometry.triangulation import _dlt, _normalized_obs, _rt


@dataclass(frozen=True)
class AssociationConfig:
    """Settings of :func:`associate` (see the module docstring).

    Attributes:
        min_views: fewest views of a hypothesis (>= 2).
        tolerance_px: the pixel tolerance of points given without their own tolerances.
        max_size_ratio: largest ratio between the animal's sizes in mm seen from two views
            (with ``sizes``).
        max_hypotheses: stop after this many hypotheses (None: as many as agree).
    """

    min_views: int = 2
    tolerance_px: float = 12.0
    max_size_ratio: float = 2.0
    max_hypotheses: int | None = None

    def __post_init__(self) -> None:
        if self.min_views < 2:
            raise ValueError(
                f"min_views must be >= 2 (a 3D point needs two views), got {self.min_views}"
            )
        if not self.tolerance_px > 0:
            raise ValueError(f"tolerance_px must be positive, got {self.tolerance_px}")
        if not self.max_size_ratio > 1:
            raise ValueError(f"max_size_ratio must be > 1, got {self.max_size_ratio}")
        if self.max_hypotheses is not None and self.max_hypotheses < 1:
            raise ValueError(f"max_hypotheses must be >= 1 or None, got {self.max_hypotheses}")


@dataclass(frozen=True, eq=False)
class Association:
    """3D hypotheses formed from the points of all views, best first.

    Attributes:
        points: (H, 3) world mm, triangulated from the members.
        members: (H, C) int64, per view the index of the point that belongs to the
            hypothesis; -1 where the view has none (hidden, missed, or its point taken).
        errors: (H, C) reprojection error of each member in pixels; NaN without a member.
        n_views: (H,) how many views have a member.
        sizes_mm: (H,) the animal's size in mm (median over the members; NaN without sizes).
        leftover: (C,) per view the indices of the points in no hypothesis.
    """

    points: np.ndarray
    members: np.ndarray
    errors: np.ndarray
    n_views: np.ndarray
    sizes_mm: np.ndarray
    leftover: tuple[np.ndarray, ...]

    def __len__(self) -> int:
        return len(self.points)


@dataclass(frozen=True, eq=False)
class _Points:
    """The points of all views padded to M per view.

    uv and the undistorted normalized xy (C, M, 2); tol, size, score (C, M); ok (C, M)
    where there is a point.
    """

    uv: np.ndarray
    xy: np.ndarray
    tol: np.ndarray
    size: np.ndarray
    score: np.ndarray
    ok: np.ndarray


def _per_view(
    values: Sequence[np.ndarray] | None, counts: list[int], what: str
) -> list[np.ndarray] | None:
    if values is None:
        return None
    if len(values) != len(counts):
        raise ValueError(f"{what} must have one entry per view ({len(counts)}), got {len(values)}")
    out = []
    for c, (v, n) in enumerate(zip(values, counts, strict=True)):
        a = np.asarray(v, dtype=np.float64).reshape(-1)
        if len(a) != n:
            raise ValueError(f"{what}[{c}] has {len(a)} entries for {n} points")
        out.append(a)
    return out


def _pad(
    points: Sequence[np.ndarray],
    tolerances: Sequence[np.ndarray] | None,
    sizes: Sequence[np.ndarray] | None,
    scores: Sequence[np.ndarray] | None,
    cfg: AssociationConfig,
    rig: CameraRig,
) -> _Points:
    pts = []
    for c, p in enumerate(points):
        a = np.asarray(p, dtype=np.float64)
        if a.size == 0:
            a = a.reshape(0, 2)
        if a.ndim != 2 or a.shape[1] != 2:
            raise ValueError(f"points[{c}] must have shape (n, 2), got {a.shape}")
        pts.append(a)
    counts = [len(p) for p in pts]
    tol_l = _per_view(tolerances, counts, "tolerances")
    size_l = _per_view(sizes, counts, "sizes")
    score_l = _per_view(scores, counts, "scores")
    c, m = len(pts), max(counts + [1])
    uv = np.full((c, m, 2), np.nan)
    tol = np.full((c, m), cfg.tolerance_px)
    size = np.full((c, m), np.nan)
    score = np.ones((c, m))
    for i, n in enumerate(counts):
        uv[i, :n] = pts[i]
        if tol_l is not None:
            tol[i, :n] = tol_l[i]
        if size_l is not None:
            size[i, :n] = size_l[i]
        if score_l is not None:
            score[i, :n] = score_l[i]
    ok = np.isfinite(uv).all(-1) & np.isfinite(tol) & (tol > 0)
    ok[:, :] &= np.arange(m)[None, :] < np.asarray(counts)[:, None]
    xy = _normalized_obs(uv.transpose(1, 0, 2), rig).transpose(1, 0, 2)
    return _Points(uv, xy, tol, size, score, ok)


def _depths(X: np.ndarray, rig: CameraRig) -> np.ndarray:
    """Depths (H, C) of points X (H, 3) in every camera."""
    return np.einsum("cij,hj->hci", rig.R, X)[..., 2] + rig.t[None, :, 2]


def _proposals(
    P: _Points, rig: CameraRig, bounds: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """Pair triangulations that pass the epipolar check: X (N, 3), seeds (N, 2, 2) (view, idx)."""
    c = P.ok.shape[0]
    seeds = [
        ((i, a), (j, b))
        for i, j in itertools.combinations(range(c), 2)
        for a, b in itertools.product(np.flatnonzero(P.ok[i]), np.flatnonzero(P.ok[j]))
    ]
    if not seeds:
        return np.zeros((0, 3)), np.zeros((0, 2, 2), np.int64)
    S = np.asarray(seeds, dtype=np.int64)
    n = np.arange(len(S))
    xy = np.full((len(S), c, 2), np.nan)
    w = np.zeros((len(S), c))
    for k in range(2):
        xy[n, S[:, k, 0]] = P.xy[S[:, k, 0], S[:, k, 1]]
        w[n, S[:, k, 0]] = 1.0
    X = _dlt(xy, _rt(rig), w)
    uv = project_rig(X[:, None, :], rig)[:, :, 0, :]  # (N, C, 2)
    keep = np.isfinite(X).all(-1)
    depth = _depths(X, rig)
    for k in range(2):
        v, idx = S[:, k, 0], S[:, k, 1]
        err = np.linalg.norm(uv[n, v] - P.uv[v, idx], axis=-1)
        keep &= (depth[n, v] > 0) & (err < P.tol[v, idx])
    if bounds is not None:
        keep &= _inside(X, bounds)
    return X[keep], S[keep]


def _inside(X: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """Whether points X (N, 3) lie in the box ``bounds`` (3, 2)."""
    return np.asarray(((bounds[:, 0] <= X) & (bounds[:, 1] >= X)).all(-1))


def _verify(
    X: np.ndarray, P: _Points, free: np.ndarray, rig: CameraRig, f: np.ndarray, max_ratio: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Members (H, C) (-1: none), errors (H, C) and sizes in mm (H,) of hypotheses X (H, 3)."""
    uv = project_rig(X[:, None, :], rig)[:, :, 0, :]  # (H, C, 2)
    depth = _depths(X, rig)
    err = np.linalg.norm(uv[:, :, None, :] - P.uv[None], axis=-1)  # (H, C, M)
    inl = free[None] & np.isfinite(err) & (err < P.tol[None]) & (depth[..., None] > 0)
    rel = np.where(inl, err / P.tol[None], np.inf)
    best = np.argmin(rel, axis=-1)  # (H, C)
    has = np.isfinite(np.min(rel, axis=-1))
    h = np.arange(len(X))[:, None]
    c = np.arange(P.ok.shape[0])[None, :]
    mm = P.size[c, best] * depth / f[None]  # (H, C), NaN without sizes
    mm = np.where(has, mm, np.nan)
    size = _row_medians(mm)
    if np.isfinite(mm).any():
        ratio = np.maximum(mm / size[:, None], size[:, None] / mm)
        has &= ~(np.isfinite(ratio) & (ratio > max_ratio))
    members = np.where(has, best, -1)
    errors = np.where(has, err[h, c, best], np.nan)
    return members, errors, size


def _row_medians(a: np.ndarray) -> np.ndarray:
    """Median of the finite values of each row of a (H, C); NaN for rows without any."""
    srt = np.sort(np.where(np.isfinite(a), a, np.inf), axis=1)
    n = np.isfinite(a).sum(1)
    lo = srt[np.arange(len(a)), np.maximum((n - 1) // 2, 0)]
    hi = srt[np.arange(len(a)), np.maximum(n // 2, 0)]
    return np.where(n > 0, (lo + hi) / 2, np.nan)


def _refit(
    X: np.ndarray,
    members: np.ndarray,
    P: _Points,
    free: np.ndarray,
    rig: CameraRig,
    f: np.ndarray,
    cfg: AssociationConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Re-triangulate one hypothesis from its members and verify it again (twice)."""
    c = np.arange(len(members))
    errors = np.full(len(members), np.nan)
    size = np.array(np.nan)
    for _ in range(2):
        has = members >= 0
        obs = np.where(has[:, None], P.xy[c, np.maximum(members, 0)], np.nan)
        w = np.where(has, P.score[c, np.maximum(members, 0)], 0.0)
        Xr = _dlt(obs[None], _rt(rig), (np.maximum(w, 1e-3) * has)[None])[0]
        if not np.isfinite(Xr).all():
            break
        m2, e2, s2 = _verify(Xr[None], P, free, rig, f, cfg.max_size_ratio)
        if (m2[0] >= 0).sum() < cfg.min_views:
            break
        X, members, errors, size = Xr, m2[0], e2[0], s2[0]
    if not np.isfinite(errors).any():
        _, e2, s2 = _verify(X[None], P, free, rig, f, cfg.max_size_ratio)
        errors = np.where(members >= 0, e2[0], np.nan)
        size = s2[0]
    return X, members, errors, np.asarray(size)


def associate(
    points: Sequence[np.ndarray],
    rig: CameraRig,
    tolerances: Sequence[np.ndarray] | None = None,
    sizes: Sequence[np.ndarray] | None = None,
    scores: Sequence[np.ndarray] | None = None,
    config: AssociationConfig | None = None,
    bounds: np.ndarray | None = None,
) -> Association:
    """Group the points of all views into 3D hypotheses (see the module docstring).

    Args:
        points: C arrays (n_c, 2) of observed pixels (box centres or one keypoint).
        rig: the cameras (C).
        tolerances: C arrays (n_c,) pixel tolerances per point (default
            ``config.tolerance_px``); a box centre is only as exact as its box.
        sizes: C arrays (n_c,) box sizes in pixels (e.g. ``sqrt(w * h)``): enables the 3D
            size check.
        scores: C arrays (n_c,) confidences, weights of the final triangulation.
        config: thresholds and limits.
        bounds: (3, 2) world box ``[[x0, x1], [y0, y1], [z0, z1]]`` mm hypotheses must lie in.

    Returns:
        The :class:`Association`, hypotheses in the order they were chosen (most views first).
    """
    cfg = config or AssociationConfig()
    if len(points) != len(rig):
        raise ValueError(f"expected points for {len(rig)} cameras ({rig.names}), got {len(points)}")
    bnd = None if bounds is None else np.asarray(bounds, dtype=np.float64).reshape(3, 2)
    P = _pad(points, tolerances, sizes, scores, cfg, rig)
    f = np.sqrt(np.abs(rig.K[:, 0, 0] * rig.K[:, 1, 1]))
    X, seeds = _proposals(P, rig, bnd)
    free = P.ok.copy()
    out_x: list[np.ndarray] = []
    out_m: list[np.ndarray] = []
    out_e: list[np.ndarray] = []
    out_s: list[float] = []
    limit = cfg.max_hypotheses or np.iinfo(np.int64).max
    while len(X) and len(out_x) < limit:
        members, errors, _ = _verify(X, P, free, rig, f, cfg.max_size_ratio)
        count = (members >= 0).sum(-1)
        rel = errors / P.tol[np.arange(len(rig)), np.maximum(members, 0)]
        quality = np.where(count > 0, np.nansum(rel, axis=1) / np.maximum(count, 1), np.inf)
        h = int(np.lexsort((quality, -count))[0])
        if count[h] < cfg.min_views:
            break
        Xh, mh, eh, sh = _refit(X[h], members[h], P, free, rig, f, cfg)
        if bnd is not None and not _inside(Xh[None], bnd)[0]:  # the refit left the bounds
            X, seeds = np.delete(X, h, axis=0), np.delete(seeds, h, axis=0)
            continue
        out_x.append(Xh)
        out_m.append(mh)
        out_e.append(eh)
        out_s.append(float(sh))
        views = np.flatnonzero(mh >= 0)
        free[views, mh[views]] = False
        alive = free[seeds[:, 0, 0], seeds[:, 0, 1]] & free[seeds[:, 1, 0], seeds[:, 1, 1]]
        X, seeds = X[alive], seeds[alive]
    c = len(rig)
    members_arr = np.asarray(out_m, dtype=np.int64).reshape(-1, c)
    leftover = tuple(np.flatnonzero(free[i]) for i in range(c))
    return Association(
        points=np.asarray(out_x, dtype=np.float64).reshape(-1, 3),
        members=members_arr,
        errors=np.asarray(out_e, dtype=np.float64).reshape(-1, c),
        n_views=(members_arr >= 0).sum(-1),
        sizes_mm=np.asarray(out_s, dtype=np.float64),
        leftover=leftover,
    )
