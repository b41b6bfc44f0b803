"""Identities over a whole recording: the swaps of the frame-by-frame tracker undone.

:func:`freipose.predict.tracking.track_animals` links each frame's hypotheses to the tracks
of the frame before. Where two animals come close, stand in one blob or one is hidden, it
can exchange them, and every frame after carries the wrong identity. :func:`resolve_identities`
looks at the whole recording at once. Per frame, which animal each track follows is a
permutation of the A animals (A! states); a hidden Markov model scores a sequence of states
by

* **appearance**: each track's coat features (:func:`~freipose.predict.tracking.colour_features`)
  against one model per animal, learnt from the recording itself (k-means of the features,
  refined from the decoded identities); per frame and track the squared distance in units of
  the typical distance to the nearest model, capped so that a blob of two coats decides
  little;
* **motion**: each animal's jump from one frame to the next under the two frames' states,
  ``(jump / motion_sigma_mm)^2 / 2``, capped: a change of state exactly where the
  frame-by-frame tracker exchanged two animals keeps both continuous, one frame early or
  late makes both jump;
* **changes**: a track's animal may change only where the track is *ambiguous* (within
  ``contact_mm`` of another track, an unmatched one where it was last seen, or unmatched
  itself in this frame or the one before), at ``swap_cost`` per track changed.

The Viterbi algorithm finds the best sequence; the appearance models are learnt again from
it, a few times. The tracks are then reordered per frame so that track ``a`` follows animal
``a`` throughout (animal ``a`` being the one that input track ``a`` follows most), and the
frames where the identities were corrected are flagged.

Shapes: T frames, A animals (tracks), S = A! states, F features.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.cluster.vq import kmeans2
from scipy.optimize import linear_sum_assignment

MAX_ANIMALS = 4  # 4! = 24 states; more animals are left as the frame-by-frame tracker made them
APPEARANCE_CAP = 9.0  # largest appearance cost of one track in one frame
MOTION_CAP = 10.0  # largest motion cost of one animal between two frames
ITERATIONS = 5


@dataclass(frozen=True)
class IdentityResolution:
    """What :func:`resolve_identities` did.

    Attributes:
        order: (T, A) int64 per frame the input track that follows animal ``a``.
        corrected: (T, A) bool, the frames where an animal changed track (output order).
        changes: the number of frames with a correction.
        separation: distance between the two closest appearance models in units of the
            typical distance of a feature to its model (NaN: no appearance); below about
            2 the coats hardly tell the animals apart and motion decides.
        margin: (T, A) per frame and animal (output order), where the animal's track is
            in contact or lost (inf elsewhere: no exchange can happen there), how much
            more the best sequence costs in which another animal is in this one's place
            than at the first frame: near 0 where neither coats nor motion can tell
            whether the animals were exchanged.
    """

    order: np.ndarray
    corrected: np.ndarray
    changes: int
    separation: float
    margin: np.ndarray


def track_features(hypothesis: np.ndarray, features: Sequence[np.ndarray]) -> np.ndarray | None:
    """(T, A, F) the features of each track's matched hypothesis (NaN: unmatched or none).

    Args:
        hypothesis: (T, A) int64 matched hypothesis per frame and track, -1 none.
        features: T arrays (H_t, F).

    Returns:
        The array, or None when no frame has a feature.
    """
    dims = [np.shape(f)[-1] for f in features if np.ndim(f) == 2 and np.shape(f)[0]]
    if not dims:
        return None
    t_n, a_n = hypothesis.shape
    out = np.full((t_n, a_n, dims[0]), np.nan)
    for t in range(t_n):
        h = hypothesis[t]
        m = h >= 0
        if m.any():
            out[t, m] = np.asarray(features[t], dtype=np.float64)[h[m]]
    return out


def _ambiguous(centers: np.ndarray, contact_mm: float) -> np.ndarray:
    """(T, A) tracks that may exchange animals in a frame.

    A track is ambiguous where it is unmatched (now or one frame before), or within
    ``contact_mm`` of another track, an unmatched track counting where it was last seen
    (the blob of two animals that one track follows while the other is unmatched).
    """
    t_n, a_n = centers.shape[:2]
    seen = np.isfinite(centers).all(-1)
    last = centers.copy()
    for t in range(1, t_n):
        last[t, ~seen[t]] = last[t - 1, ~seen[t]]
    d = np.linalg.norm(last[:, :, None] - last[:, None], axis=-1)
    d[:, np.arange(a_n), np.arange(a_n)] = np.inf
    amb = (np.where(np.isnan(d), np.inf, d) < contact_mm).any(-1) | ~seen
    amb[1:] |= ~seen[:-1]
    return amb


def _appearance_costs(
    feats: np.ndarray, ident: np.ndarray | None, perms: np.ndarray
) -> tuple[np.ndarray, float]:
    """(T, S) appearance cost of every state, and the models' separation.

    The models are k-means centres of the features (``ident`` None), or the mean features
    of each animal under the decoded identities ``ident`` (T, A).
    """
    t_n, a_n = feats.shape[:2]
    ok = np.isfinite(feats).all(-1)
    if ok.sum() < 2 * a_n:
        return np.zeros((t_n, len(perms))), float("nan")
    if ident is None:
        z = feats[ok]
        rng = np.random.default_rng(0)
        fits = [kmeans2(z, a_n, minit="++", seed=rng) for _ in range(5)]
        models = min(fits, key=lambda f: float(((z - f[0][f[1]]) ** 2).sum()))[0]
    else:
        models = np.stack([
            feats[ok & (ident == a)].mean(0) if (ok & (ident == a)).any() else
            np.full(feats.shape[-1], np.nan) for a in range(a_n)
        ])  # fmt: skip
    d2 = ((feats[:, :, None, :] - models[None, None]) ** 2).sum(-1)  # (T, A, A)
    near2 = np.nanmin(np.where(np.isnan(d2), np.inf, d2), -1)
    scale = float(np.median(near2[ok & np.isfinite(near2)]))
    scale = scale if scale > 0 else 1.0
    cost = np.where(ok[..., None] & np.isfinite(d2), np.minimum(d2 / scale, APPEARANCE_CAP), 0.0)
    per_state = np.stack([cost[:, np.arange(a_n), p].sum(-1) for p in perms], 1)
    md = np.linalg.norm(models[:, None] - models[None], axis=-1)
    md[np.arange(a_n), np.arange(a_n)] = np.inf
    return per_state, float(np.nanmin(md) / np.sqrt(scale))


def _step_costs(
    centers: np.ndarray, amb: np.ndarray, perms: np.ndarray, swap_cost: float, sigma: float
) -> Callable[[int], np.ndarray]:
    """A function t -> (S, S) cost of going from each state at t - 1 to each state at t."""
    carrier = np.argsort(perms, axis=1)  # (S, A) the track that follows animal a
    changed = perms[:, None, :] != perms[None, :, :]  # (S from, S to, A tracks)
    n_changed = changed.sum(-1)

    def step(t: int) -> np.ndarray:
        before = centers[t - 1][carrier]  # (S, A, 3) animal a's place under each state
        now = centers[t][carrier]
        jump = np.linalg.norm(before[:, None] - now[None], axis=-1)  # (S, S, A)
        motion = np.nan_to_num(np.minimum((jump / sigma) ** 2 / 2, MOTION_CAP), nan=0.0)
        allowed = ~(changed & ~amb[t]).any(-1)
        return np.where(allowed, swap_cost * n_changed, np.inf) + motion.sum(-1)

    return step


def _best_path(
    unary: np.ndarray, step: Callable[[int], np.ndarray], first: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The forward pass of the Viterbi algorithm and the best state per frame.

    Args:
        unary: (T, S) cost of each state in each frame.
        step: t -> (S, S) cost of going from each state at t - 1 to each state at t.
        first: the only state allowed in the first frame (None: any).

    Returns:
        ``(fwd, states)``: (T, S) the best cost of a sequence ending in each state, and (T,)
        the best sequence.
    """
    t_n, s_n = unary.shape
    fwd = np.full((t_n, s_n), np.inf)
    if first is None:
        fwd[0] = unary[0]
    else:
        fwd[0, first] = unary[0, first]
    back = np.zeros((t_n, s_n), dtype=np.int64)
    for t in range(1, t_n):
        total = fwd[t - 1][:, None] + step(t)
        back[t] = np.argmin(total, 0)
        fwd[t] = total[back[t], np.arange(s_n)] + unary[t]
    states = np.zeros(t_n, dtype=np.int64)
    states[-1] = int(np.argmin(fwd[-1]))
    for t in range(t_n - 1, 0, -1):
        states[t - 1] = back[t, states[t]]
    return fwd, states


def order_changes(order: np.ndarray) -> np.ndarray:
    """(T, A) bool: the frames where an animal's row differs from the frame before."""
    moved = np.zeros(order.shape, bool)
    moved[1:] = order[1:] != order[:-1]
    return moved


def _body_lengths(poses: np.ndarray) -> np.ndarray:
    """(..., A) each pose's largest distance between two keypoints, -inf without one.

    Args:
        poses: (..., A, K, 3) mm, NaN missing.
    """
    spread = np.linalg.norm(poses[..., :, None, :] - poses[..., None, :, :], axis=-1)
    return np.where(np.isfinite(spread), spread, -np.inf).max(axis=(-1, -2))


def _viterbi(
    appearance: np.ndarray,
    centers: np.ndarray,
    amb: np.ndarray,
    perms: np.ndarray,
    swap_cost: float,
    sigma: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The best state per frame (T,) and each track's identity margin (T, A).

    The margin of track i at frame t is how much more the best sequence costs in which
    track i follows another animal at t than at the first frame (the min-marginals of a
    backward pass and a forward pass that starts in the best first state): near 0 where
    the evidence cannot tell whether the animals were exchanged since.
    """
    t_n, s_n = appearance.shape
    step = _step_costs(centers, amb, perms, swap_cost, sigma)
    bwd = np.zeros((t_n, s_n))
    for t in range(t_n - 1, 0, -1):
        bwd[t - 1] = (step(t) + (appearance[t] + bwd[t])[None, :]).min(1)
    first = int(np.argmin(appearance[0] + bwd[0]))
    fwd, states = _best_path(appearance, step, first)
    through = fwd + bwd  # (T, S) best cost of a sequence through each state
    best = through[np.arange(t_n), states]
    other = perms[None, :, :] != perms[states][:, None, :]  # (T, S, A)
    alt = np.where(other, through[:, :, None], np.inf).min(1)  # (T, A)
    return states, np.maximum(alt - best[:, None], 0.0)


def resolve_identities(
    centers: np.ndarray,
    hypothesis: np.ndarray,
    features: Sequence[np.ndarray] | None,
    contact_mm: float = 150.0,
    swap_cost: float = 2.0,
    motion_sigma_mm: float = 30.0,
) -> IdentityResolution:
    """Which track follows which animal in every frame (see the module docstring).

    Args:
        centers: (T, A, 3) the tracks' centres, mm, NaN where unmatched.
        hypothesis: (T, A) int64 the tracks' matched hypotheses, -1 none.
        features: T arrays (H_t, F) the hypotheses' appearance (None: motion alone).
        contact_mm: tracks closer than this may exchange animals.
        swap_cost: cost of one track changing animal.
        motion_sigma_mm: typical jump of an animal between two frames, mm.

    Returns:
        :class:`IdentityResolution`; with one animal, more than ``MAX_ANIMALS`` or no
        frames, the identity order and no corrections.
    """
    x = np.asarray(centers, dtype=np.float64)
    t_n, a_n = x.shape[:2]
    same = np.broadcast_to(np.arange(a_n), (t_n, a_n)).copy()
    if a_n < 2 or a_n > MAX_ANIMALS or t_n < 2:
        none = np.zeros((t_n, a_n), bool)
        return IdentityResolution(same, none, 0, float("nan"), np.full((t_n, a_n), np.inf))
    perms = np.array(list(itertools.permutations(range(a_n))), dtype=np.int64)  # (S, A)
    feats = None if features is None else track_features(hypothesis, features)
    amb = _ambiguous(x, contact_mm)
    ident: np.ndarray | None = None
    states = np.zeros(t_n, dtype=np.int64)
    separation = float("nan")
    appearance = np.zeros((t_n, len(perms)))
    margin = np.zeros((t_n, a_n))
    for _ in range(ITERATIONS if feats is not None else 1):
        if feats is not None:
            appearance, separation = _appearance_costs(feats, ident, perms)
        new, margin = _viterbi(appearance, x, amb, perms, swap_cost, motion_sigma_mm)
        if ident is not None and np.array_equal(new, states):
            break
        states, ident = new, perms[new]
    ident = perms[states]  # (T, A) the animal each input track follows
    # name the animals after the tracks that follow them most: no change, no reordering
    counts = np.zeros((a_n, a_n))
    np.add.at(counts, (np.broadcast_to(np.arange(a_n), ident.shape), ident), 1)
    tracks_, animals = linear_sum_assignment(-counts)
    rename = np.empty(a_n, dtype=np.int64)
    rename[animals] = tracks_
    order = np.argsort(rename[ident], axis=1)  # (T, A) the track of animal a
    moved = order_changes(order)
    margin = np.where(amb, margin, np.inf)  # apart from the others: no exchange here
    rows = np.arange(t_n)[:, None]
    return IdentityResolution(
        order, moved, int(moved.any(1).sum()), separation, margin[rows, order]
    )


@dataclass(frozen=True)
class PoseRelabelling:
    """What :func:`relabel_by_poses` did.

    Attributes:
        order: (T, A) int64 per frame the input row that animal ``a``'s pose comes from.
        corrected: (T, A) bool, the frames where an animal's pose changed row (output order).
        changes: the number of frames with a correction.
    """

    order: np.ndarray
    corrected: np.ndarray
    changes: int


def _held(poses: np.ndarray, frames: int) -> np.ndarray:
    """(T, A, K, 3) the poses; a missing keypoint holds its row's last position.

    It holds for up to ``frames`` frames and is NaN after.
    """
    out = np.array(poses, dtype=np.float64)
    age = np.zeros(out.shape[1:3])  # (A, K) frames since each keypoint was last seen
    for t in range(1, len(out)):
        gap = ~np.isfinite(out[t]).all(-1)
        age = np.where(gap, age + 1, 0)
        fill = gap & (age <= frames)
        out[t][fill] = out[t - 1][fill]
    return out


def _short_runs(off: np.ndarray, longest: int) -> np.ndarray:
    """(T,) bool: the frames of ``off`` in runs of at most ``longest`` consecutive frames."""
    edges = np.diff(np.r_[0, off.astype(np.int8), 0])
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    keep = np.zeros(len(off), bool)
    for a, b in zip(starts, stops, strict=True):
        keep[a:b] = b - a <= longest
    return keep


def relabel_by_poses(
    poses: np.ndarray,
    fps: float,
    keep_weight: float = 0.03,
    hold_s: float = 0.5,
    longest_s: float = 1.0,
) -> PoseRelabelling:
    """Which row's pose is which animal's in every frame, from the continuity of whole poses.

    The cube of an animal in close contact holds parts of the other animals, and its pose can
    come out as another animal's (while that animal's cube gives this one's): the tracks
    stayed right, the poses exchanged rows for a frame or a few. Per frame the assignment of
    rows to animals is a permutation (A! states); the Viterbi algorithm finds the sequence
    that minimises the sum over frames and animals of the RMS distance of an animal's
    keypoints from the frame before, plus ``keep_weight`` x the animals' median body length
    (the largest distance between two keypoints) per frame that departs from the rows' own
    order: an exchange is made only where it makes the whole poses move markedly less. A
    missing keypoint holds its last position for up to ``hold_s``; after a longer gap it
    does not count. Exchanges that last longer than ``longest_s`` are not made: an exchange
    of identities over a long stretch is the tracker's decision (made from the coats and the
    motion of the whole recording, :func:`resolve_identities`), not a stray of the poses.

    Args:
        poses: (T, A, K, 3) per frame and row (the tracks' order) the pose, mm, NaN missing.
        fps: frame rate.
        keep_weight: cost of a frame out of the rows' order, in body lengths.
        hold_s: longest gap over which a missing keypoint's last position counts, seconds.
        longest_s: longest exchange made, seconds.

    Returns:
        :class:`PoseRelabelling`; with one animal, more than ``MAX_ANIMALS``, fewer than two
        frames or no pose at all, the rows' own order and no corrections.
    """
    x = np.asarray(poses, dtype=np.float64)
    if x.ndim != 4 or x.shape[-1] != 3:
        raise ValueError(f"poses must be (T, A, K, 3), got {x.shape}")
    t_n, a_n = x.shape[:2]
    same = np.broadcast_to(np.arange(a_n), (t_n, a_n)).copy()
    none = PoseRelabelling(same, np.zeros((t_n, a_n), bool), 0)
    if a_n < 2 or a_n > MAX_ANIMALS or t_n < 2 or not np.isfinite(x).any():
        return none
    per = _body_lengths(x[:: max(t_n // 1000, 1)])  # from up to about 1000 frames
    length = float(np.median(per[np.isfinite(per)])) if np.isfinite(per).any() else 0.0
    perms = np.array(list(itertools.permutations(range(a_n))), dtype=np.int64)  # (S, A)
    keep = keep_weight * length * (perms != np.arange(a_n)).any(1)  # (S,)
    held = _held(x, int(round(hold_s * fps)))

    def step(t: int) -> np.ndarray:
        d = held[t - 1][:, None] - held[t][None]  # (A, A, K, 3): row i at t-1 to row j at t
        sq = np.sum(d * d, axis=-1)
        ok = np.isfinite(sq)
        rms = np.sqrt(np.where(ok, sq, 0.0).sum(-1) / np.maximum(ok.sum(-1), 1))  # (A, A)
        return rms[perms[:, None, :], perms[None, :, :]].sum(-1)  # (S, S)

    _, states = _best_path(np.broadcast_to(keep, (t_n, len(perms))), step)
    order = perms[states]
    off = (order != np.arange(a_n)).any(1)
    order = np.where(_short_runs(off, max(int(round(longest_s * fps)), 1))[:, None], order, same)
    moved = order_changes(order)
    return PoseRelabelling(order, moved, int(moved.any(1).sum()))


def coincident_poses(poses: np.ndarray, fraction: float = 0.1) -> np.ndarray:
    """(B, A) bool: the rows whose pose lies on another row's (one animal found twice).

    Two animals cannot share their space: two poses whose keypoints lie, in the median,
    within ``fraction`` of a body length (the larger of the two poses' largest distance
    between two keypoints) of the same keypoints of the other are one animal's pose twice,
    and the other animal was missed there.

    Args:
        poses: (B, A, K, 3) per frame and row the pose, mm, NaN missing.
        fraction: the distance, in body lengths.
    """
    x = np.asarray(poses, dtype=np.float64)
    b_n, a_n = x.shape[:2]
    out = np.zeros((b_n, a_n), bool)
    length = _body_lengths(x)  # (B, A)
    for i, j in itertools.combinations(range(a_n), 2):
        d = np.linalg.norm(x[:, i] - x[:, j], axis=-1)  # (B, K)
        ok = np.isfinite(d)
        med = np.array([np.median(r[k]) if k.any() else np.inf for r, k in zip(d, ok, strict=True)])
        near = med < fraction * np.maximum(length[:, i], length[:, j])
        out[:, i] |= near
        out[:, j] |= near
    return out
