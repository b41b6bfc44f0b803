"""Identity over time: several animals' 3D hypotheses linked into one track per animal.

Per frame the detection gives H 3D hypotheses (:func:`freipose.detect.multi.detect_animals`)
in no particular order; :func:`track_animals` keeps A tracks, one per animal:

* **motion**: each track predicts its centre with a constant velocity (the velocity is
  smoothed over matches, capped at ``max_speed``, and decays while the animal is unseen);
  while a track is in contact with another (a hypothesis within ``contact_mm`` of another
  track's prediction: it may be the blob of both) its velocity is kept, not learnt;
* **appearance** (optional): each track keeps a running mean of its hypotheses' feature
  vectors (e.g. :func:`colour_features` of the crops, or body size), updated only while the
  animal is apart from the others, so a blob of two animals in contact does not blend
  their coats;
* **assignment**: the cost of hypothesis j for track i is its distance from the prediction
  over ``gate_mm`` plus ``appearance_weight`` x the appearance distance; pairs farther than
  the track's gate (``gate_mm``, growing by ``gate_growth_mm`` per unseen frame) are
  forbidden; leaving a track unmatched costs ``miss_cost`` (growing with the time unseen),
  and the Hungarian algorithm (:func:`scipy.optimize.linear_sum_assignment`) picks the
  matches. Tracks are started from hypotheses far from every existing track until there
  are A of them;
* **reacquisition**: a track unmatched for two frames takes a hypothesis that no track
  follows, lies farther than the gate from every matched one and was there in the previous
  frame too (an animal whose track was lost, e.g. it followed the other animal out of a
  contact; a false hypothesis seldom lasts two frames): by appearance where known,
  restarting with no velocity;
* **identity confidence**: per matched track, how much more the best alternative would
  cost (exchanging hypotheses with another track, or taking an unmatched hypothesis):
  ``1 - exp(-margin / confidence_scale)``. Close contact with similar motion and look
  gives a margin near 0: the frame is *flagged* (confidence below ``flag_below``), where
  an identity swap cannot be ruled out;
* **the whole recording** (``resolve``): the frame-by-frame pass can still exchange two
  animals in a long contact; :func:`freipose.predict.identity.resolve_identities` then
  decides, over the whole recording, which animal each track follows in every frame (from
  the coats and the continuity of every animal's motion) and reorders the tracks; the
  frames where it moved an animal to another track are flagged, and so are those where
  another animal would fit the track almost as well (``flag_margin``).

Shapes: T frames, A animals (tracks), H_t hypotheses at frame t, C cameras, F features.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

from freipose.errors import FreiPoseError
from freipose.predict.identity import resolve_identities

FORBIDDEN = 1e6  # cost of a pair beyond the gate


class TrackingError(FreiPoseError):
    """Tracking inputs or settings that do not fit; the message says why."""


@dataclass(frozen=True)
class TrackingConfig:
    """Settings of :func:`track_animals` (see the module docstring).

    Attributes:
        gate_mm: largest distance of a match from the prediction, mm.
        gate_growth_mm: the gate grows by this per unseen frame, mm.
        max_speed: fastest speed of an animal, mm/s (caps the velocity).
        velocity_smoothing: weight of the newest velocity in the smoothed one (0..1].
        velocity_decay: the velocity is multiplied by this per unseen frame.
        appearance_weight: cost of an appearance distance of 1 (in gate units).
        appearance_rate: weight of a new feature vector in a track's running mean.
        contact_mm: tracks closer than this are in contact (appearance not updated).
        confidence_scale: cost margin (gate units) of confidence ``1 - 1/e``.
        flag_below: confidence below which a frame is flagged.
        flag_margin: a frame is also flagged where the whole-recording pass could place
            another animal in this track at less than this extra cost (its ``margin``);
            an exchange of two tracks costs ``2 * swap_cost`` by itself, so the default
            flags where the coats and the motion add less than 1 to that.
        miss_cost: cost of leaving a track unmatched (gate units) ...
        miss_cost_per_s: ... growing by this per second unseen, so that a long-lost animal
            is found again farther away, but a false hypothesis far from a track just
            hidden does not take it.
        reacquire: a lost track takes an animal no track follows (see the module
            docstring).
        resolve: after the frame-by-frame pass, undo its swaps over the whole recording
            (:func:`freipose.predict.identity.resolve_identities`, up to 4 animals).
        swap_cost: cost of one track changing animal in that pass.
        motion_sigma_mm: typical jump of an animal between two frames in that pass, mm.
    """

    gate_mm: float = 100.0
    gate_growth_mm: float = 15.0
    max_speed: float = 1500.0
    velocity_smoothing: float = 0.5
    velocity_decay: float = 0.97
    appearance_weight: float = 1.0
    appearance_rate: float = 0.1
    contact_mm: float = 150.0
    confidence_scale: float = 0.3
    flag_below: float = 0.5
    flag_margin: float = 5.0
    miss_cost: float = 1.0
    miss_cost_per_s: float = 1.0
    reacquire: bool = True
    resolve: bool = True
    swap_cost: float = 2.0
    motion_sigma_mm: float = 30.0

    def __post_init__(self) -> None:
        for name in ("gate_mm", "max_speed", "confidence_scale", "motion_sigma_mm"):
            if not getattr(self, name) > 0:
                raise TrackingError(f"{name} must be positive, got {getattr(self, name)}")
        for name in ("velocity_smoothing", "appearance_rate"):
            if not 0 < getattr(self, name) <= 1:
                raise TrackingError(f"{name} must be in (0, 1], got {getattr(self, name)}")
        if not 0 <= self.velocity_decay <= 1:
            raise TrackingError(f"velocity_decay must be in [0, 1], got {self.velocity_decay}")
        if min(self.gate_growth_mm, self.appearance_weight, self.contact_mm, self.swap_cost) < 0:
            raise TrackingError(
                "gate_growth_mm, appearance_weight, contact_mm and swap_cost must be >= 0"
            )


@dataclass(frozen=True, eq=False)
class Tracks:
    """One track per animal over T frames.

    Attributes:
        centers: (T, A, 3) world mm of the matched hypothesis; NaN where unmatched.
        boxes: (T, A, C, 4) the matched hypothesis' boxes (NaN where unmatched; C = 0
            when no boxes were given).
        hypothesis: (T, A) int64 index of the matched hypothesis in its frame, -1 none.
        confidence: (T, A) identity confidence in [0, 1]; NaN where unmatched.
        flagged: (T, A) confidence below ``flag_below`` (a swap cannot be ruled out), the
            frame where the whole-recording pass moved the animal to this track, or a
            contact where that pass could not tell whether animals were exchanged
            (``flag_margin``).
        fps: frames per second.
    """

    centers: np.ndarray
    boxes: np.ndarray
    hypothesis: np.ndarray
    confidence: np.ndarray
    flagged: np.ndarray
    fps: float

    @property
    def observed(self) -> np.ndarray:
        """(T, A) whether the animal was matched in the frame."""
        return self.hypothesis >= 0

    @property
    def num_animals(self) -> int:
        """A, the number of tracks."""
        return int(self.hypothesis.shape[1])


@dataclass
class _Track:
    """The mutable state of one track during :func:`track_animals`."""

    pos: np.ndarray
    vel: np.ndarray
    unseen: int = 0
    feature: np.ndarray | None = None

    def predict(self) -> np.ndarray:
        return self.pos + self.vel * (self.unseen + 1)


def _costs(
    tracks: list[_Track], X: np.ndarray, feats: np.ndarray | None, cfg: TrackingConfig
) -> np.ndarray:
    """Cost (N, H) of every hypothesis for every track (FORBIDDEN beyond the gate)."""
    if not tracks or not len(X):
        return np.zeros((len(tracks), len(X)))
    pred = np.stack([tr.predict() for tr in tracks])
    gate = cfg.gate_mm + cfg.gate_growth_mm * np.array([tr.unseen for tr in tracks])
    d = np.linalg.norm(pred[:, None] - X[None], axis=-1)
    cost = d / cfg.gate_mm
    if feats is not None and cfg.appearance_weight > 0:
        for i, tr in enumerate(tracks):
            if tr.feature is not None:
                look = np.linalg.norm(feats - tr.feature, axis=-1)
                if np.isfinite(look).any():  # relative: the look chooses, motion gates
                    look = np.nan_to_num(look - np.nanmin(look), nan=0.0)
                    cost[i] += cfg.appearance_weight * look
    return np.where(d <= gate[:, None], cost, FORBIDDEN)


def _assign(cost: np.ndarray, miss: np.ndarray) -> np.ndarray:
    """Hungarian matching (N,) hypothesis per track (-1: none) with a miss cost (N,) per track."""
    n, h = cost.shape
    match = np.full(n, -1, dtype=np.int64)
    if not n or not h:
        return match
    dummy = np.full((n, n), FORBIDDEN)
    np.fill_diagonal(dummy, miss)
    full = np.concatenate([cost, dummy], axis=1)
    rows, cols = linear_sum_assignment(full)
    ok = (cols < h) & (full[rows, cols] < FORBIDDEN)
    match[rows[ok]] = cols[ok]
    return match


def _margins(cost: np.ndarray, match: np.ndarray, miss: np.ndarray) -> np.ndarray:
    """Per track the extra cost of its best alternative (inf: none); match (N,) hypothesis or -1."""
    n, h = cost.shape
    out = np.full(n, np.inf)
    taken = set(int(j) for j in match if j >= 0)
    for i in range(n):
        j = match[i]
        if j < 0:
            continue
        c0 = cost[i, j]
        out[i] = miss[i] - c0  # left unmatched
        for jj in set(range(h)) - taken:  # an unmatched hypothesis instead
            out[i] = min(out[i], cost[i, jj] - c0)
        for k in range(n):  # exchange with another track
            if k == i:
                continue
            jk = match[k]
            # with an unmatched track k: k takes this hypothesis and i none
            alt = cost[i, jk] + cost[k, j] - cost[k, jk] if jk >= 0 else cost[k, j]
            out[i] = min(out[i], alt - c0)
    return np.maximum(out, 0.0)


def _update(tr: _Track, x: np.ndarray, f: np.ndarray | None, alone: bool, cfg: TrackingConfig,
            fps: float) -> None:  # fmt: skip
    """Move a track to its match ``x``; velocity and look are learnt only while it is alone."""
    if alone:
        step = (x - tr.pos) / (tr.unseen + 1)
        v = cfg.velocity_smoothing * step + (1 - cfg.velocity_smoothing) * tr.vel
        vmax = cfg.max_speed / fps
        speed = float(np.linalg.norm(v))
        tr.vel = v * min(1.0, vmax / speed) if speed > 0 else v
    tr.pos = np.asarray(x, dtype=np.float64).copy()
    tr.unseen = 0
    if f is not None and np.isfinite(f).all():
        if tr.feature is None:
            tr.feature = np.asarray(f, dtype=np.float64).copy()
        elif alone:
            tr.feature = (1 - cfg.appearance_rate) * tr.feature + cfg.appearance_rate * f


def _frame_inputs(
    centers: Sequence[np.ndarray], features: Sequence[np.ndarray] | None, t: int
) -> tuple[np.ndarray, np.ndarray | None]:
    X = np.asarray(centers[t], dtype=np.float64).reshape(-1, 3)
    ok = np.isfinite(X).all(-1)
    X = np.where(ok[:, None], X, 1e12)  # a hypothesis without a centre is never matched
    F = None
    if features is not None:
        F = np.asarray(features[t], dtype=np.float64)
        F = F.reshape(len(X), -1) if len(X) else F.reshape(0, F.shape[-1] if F.ndim else 0)
    return X, F


def track_animals(
    centers: Sequence[np.ndarray],
    n_animals: int,
    fps: float,
    features: Sequence[np.ndarray] | None = None,
    boxes: Sequence[np.ndarray] | None = None,
    config: TrackingConfig | None = None,
) -> Tracks:
    """Link per-frame 3D hypotheses into ``n_animals`` tracks (see the module docstring).

    Args:
        centers: T arrays (H_t, 3) world mm: each frame's hypotheses (any order).
        n_animals: how many animals (A).
        fps: frames per second.
        features: T arrays (H_t, F) appearance vectors of the hypotheses (NaN rows: none).
        boxes: T arrays (H_t, C, 4) the hypotheses' boxes, carried into the tracks.
        config: gates, rates, thresholds.

    Returns:
        :class:`Tracks`; track ``a`` is started from the ``a``-th animal found.
    """
    cfg = config or TrackingConfig()
    if n_animals < 1:
        raise TrackingError(f"n_animals must be >= 1, got {n_animals}")
    if not (np.isfinite(fps) and fps > 0):
        raise TrackingError(f"fps must be positive, got {fps}")
    t_n = len(centers)
    for name, seq in (("features", features), ("boxes", boxes)):
        if seq is not None and len(seq) != t_n:
            raise TrackingError(f"{name} has {len(seq)} frames, centers {t_n}")
    c = 0
    if boxes is not None:
        c = next((np.shape(b)[1] for b in boxes if np.size(b)), 0)
    a_n = int(n_animals)
    out_x = np.full((t_n, a_n, 3), np.nan)
    out_b = np.full((t_n, a_n, c, 4), np.nan)
    out_h = np.full((t_n, a_n), -1, dtype=np.int64)
    out_c = np.full((t_n, a_n), np.nan)
    tracks: list[_Track] = []
    prev_free = np.zeros((0, 3))
    for t in range(t_n):
        X, F = _frame_inputs(centers, features, t)
        cost = _costs(tracks, X, F, cfg)
        unseen_s = np.array([tr.unseen for tr in tracks], dtype=np.float64) / fps
        miss = cfg.miss_cost + cfg.miss_cost_per_s * unseen_s
        match = _assign(cost, miss)
        margin = _margins(cost, match, miss)
        _reacquire(tracks, X, F, match, margin, prev_free, cfg)
        _start_tracks(tracks, X, F, match, a_n, cfg)
        match = np.concatenate([match, np.full(len(tracks) - len(match), -1)])
        for i in range(len(tracks) - len(margin)):  # started now: matched to their seed
            match[len(margin) + i] = _seed_of(tracks[len(margin) + i], X)
        margin = np.concatenate([margin, np.full(len(tracks) - len(margin), np.inf)])
        prev_free = _unclaimed(X, match)
        pos = np.stack([tr.predict() for tr in tracks]) if tracks else np.zeros((0, 3))
        for i, tr in enumerate(tracks):
            j = int(match[i])
            if j < 0:
                tr.unseen += 1
                tr.vel = tr.vel * cfg.velocity_decay
                continue
            others = np.delete(pos, i, axis=0)
            alone = not len(others) or bool(
                np.linalg.norm(others - X[j], axis=-1).min() > cfg.contact_mm
            )
            _update(tr, X[j], None if F is None else F[j], alone, cfg, fps)
            out_x[t, i], out_h[t, i] = X[j], j
            out_c[t, i] = 1.0 - np.exp(-margin[i] / cfg.confidence_scale)
            if c and boxes is not None and np.size(boxes[t]):
                out_b[t, i] = np.asarray(boxes[t])[j]
    flagged = np.nan_to_num(out_c, nan=1.0) < cfg.flag_below
    if cfg.resolve:
        res = resolve_identities(out_x, out_h, features, cfg.contact_mm, cfg.swap_cost,
                                 cfg.motion_sigma_mm)  # fmt: skip
        rows = np.arange(t_n)[:, None]
        o = res.order
        out_x, out_b, out_h = out_x[rows, o], out_b[rows, o], out_h[rows, o]
        out_c, flagged = out_c[rows, o], flagged[rows, o] | res.corrected
        flagged |= (out_h >= 0) & (res.margin < cfg.flag_margin)
    return Tracks(out_x, out_b, out_h, out_c, flagged, float(fps))


def _reacquire(
    tracks: list[_Track], X: np.ndarray, F: np.ndarray | None, match: np.ndarray,
    margin: np.ndarray, prev_free: np.ndarray, cfg: TrackingConfig,
) -> np.ndarray:  # fmt: skip
    """Lost tracks take the animals that no track follows (changes ``match`` and ``margin``).

    A hypothesis no track took, farther than ``gate_mm`` from every matched one and seen
    in the previous frame too (within ``gate_mm`` of a hypothesis no track took then: a
    false hypothesis seldom lasts), is an animal whose track was lost (e.g. it followed
    the other animal out of a contact). The tracks unmatched in this frame and the
    previous one take such hypotheses, by appearance where it is known (Hungarian), and
    restart there with no velocity; their margin is that of the appearance assignment.

    Returns:
        (N,) bool, the tracks that were reacquired.
    """
    n = len(tracks)
    got = np.zeros(n, bool)
    if not cfg.reacquire or not n or not len(X) or not len(prev_free):
        return got
    lost = np.flatnonzero((match[:n] < 0) & (np.array([tr.unseen for tr in tracks]) >= 1))
    taken = X[match[match >= 0]]
    ok = np.isfinite(X).all(-1) & (np.abs(X).max(-1) < 1e11)
    ok[match[match >= 0]] = False
    if len(taken):
        ok &= np.linalg.norm(X[:, None] - taken[None], axis=-1).min(1) > cfg.gate_mm
    ok &= np.linalg.norm(X[:, None] - prev_free[None], axis=-1).min(1) <= cfg.gate_mm
    free = np.flatnonzero(ok)
    if not len(lost) or not len(free):
        return got
    cost = np.zeros((len(lost), len(free)))
    for r, i in enumerate(lost):
        d = np.linalg.norm(X[free] - tracks[i].pos, axis=-1)
        cost[r] = 0.01 * d / cfg.gate_mm  # ties: the nearest
        if F is not None and tracks[i].feature is not None and cfg.appearance_weight > 0:
            look = np.linalg.norm(F[free] - tracks[i].feature, axis=-1)
            cost[r] += cfg.appearance_weight * np.nan_to_num(look, nan=0.0)
    rows, cols = linear_sum_assignment(cost)
    miss = np.full(len(lost), FORBIDDEN)
    sub = np.full(len(lost), -1, dtype=np.int64)
    sub[rows] = cols
    m2 = _margins(cost, sub, miss)
    for r, cidx in zip(rows, cols, strict=True):
        i, j = lost[r], free[cidx]
        tr = tracks[i]
        tr.pos, tr.vel, tr.unseen = X[j].copy(), np.zeros(3), 0
        match[i], margin[i], got[i] = j, m2[r], True
    return got


def _unclaimed(X: np.ndarray, match: np.ndarray) -> np.ndarray:
    """The finite hypotheses (n, 3) no track took in this frame."""
    ok = np.isfinite(X).all(-1) & (np.abs(X).max(-1) < 1e11) if len(X) else np.zeros(0, bool)
    ok[match[match >= 0]] = False
    return X[ok]


def _start_tracks(
    tracks: list[_Track], X: np.ndarray, F: np.ndarray | None, match: np.ndarray, n: int,
    cfg: TrackingConfig,
) -> None:  # fmt: skip
    """Start tracks from unmatched hypotheses far from every track, until there are ``n``."""
    used = set(int(j) for j in match if j >= 0)
    for j in range(len(X)):
        if len(tracks) >= n:
            return
        if j in used or not np.isfinite(X[j]).all() or np.abs(X[j]).max() >= 1e11:
            continue
        if tracks and min(np.linalg.norm(tr.predict() - X[j]) for tr in tracks) < cfg.gate_mm:
            continue
        f = None if F is None or not np.isfinite(F[j]).all() else F[j].copy()
        tracks.append(_Track(X[j].copy(), np.zeros(3), 0, f))
        used.add(j)


def _seed_of(tr: _Track, X: np.ndarray) -> int:
    return int(np.argmin(np.linalg.norm(X - tr.pos, axis=-1)))


def colour_features(
    images: Sequence[np.ndarray],
    boxes: np.ndarray,
    use: np.ndarray | None = None,
    bins: int = 6,
    masks: Sequence[np.ndarray | None] | None = None,
) -> np.ndarray:
    """Coat colour of each hypothesis: colour histograms of its boxes, over its views.

    Per box a hue-saturation histogram (``bins`` x ``bins``) and a brightness histogram
    (``bins``): hue and saturation tell coloured coats apart, brightness black from white
    (both without saturation). With ``masks`` only the foreground pixels of a box count
    (not the floor around the animal).

    Args:
        images: C BGR uint8 images (H, W, 3), one per camera.
        boxes: (H, C, 4) the hypotheses' boxes.
        use: (H, C) bool, the views to use (e.g. ``own``: not the boxes shared by two
            animals); default all finite boxes.
        bins: histogram bins per channel.
        masks: C foreground masks (H, W) bool or None (a view without: the whole box).

    Returns:
        (H, bins * bins + bins) square roots of the two histograms, each normalised and
        weighted 1/2, so that the Euclidean distance of two rows is 0..sqrt(2); NaN rows
        for hypotheses without a usable box.
    """
    b = np.asarray(boxes, dtype=np.float64)
    h, c = b.shape[:2]
    ok = np.isfinite(b).all(-1) if use is None else np.asarray(use, bool) & np.isfinite(b).all(-1)
    out = np.full((h, bins * bins + bins), np.nan)
    hsv = [cv2.cvtColor(np.asarray(img), cv2.COLOR_BGR2HSV) for img in images]
    fg = [None if masks is None or masks[v] is None else np.asarray(masks[v], np.uint8)
          for v in range(len(hsv))]  # fmt: skip
    for i in range(h):
        acc_hs, acc_v = np.zeros(bins * bins), np.zeros(bins)
        for v in np.flatnonzero(ok[i]):
            hh, ww = hsv[v].shape[:2]
            x0, y0 = max(int(b[i, v, 0] + 0.5), 0), max(int(b[i, v, 1] + 0.5), 0)
            x1, y1 = min(int(b[i, v, 2] + 0.5), ww), min(int(b[i, v, 3] + 0.5), hh)
            if x1 <= x0 or y1 <= y0:
                continue
            patch = hsv[v][y0:y1, x0:x1]
            m = None if fg[v] is None else np.ascontiguousarray(fg[v][y0:y1, x0:x1])
            if m is not None and not m.any():
                continue
            hs = cv2.calcHist([patch], [0, 1], m, [bins, bins], [0, 180, 0, 256]).ravel()
            val = cv2.calcHist([patch], [2], m, [bins], [0, 256]).ravel()
            acc_hs += hs / max(hs.sum(), 1.0)
            acc_v += val / max(val.sum(), 1.0)
        if acc_hs.sum() > 0:
            out[i] = np.sqrt(0.5 * np.r_[acc_hs / acc_hs.sum(), acc_v / acc_v.sum()])
    return out


def identity_switches(
    track_centers: np.ndarray, true_centers: np.ndarray, max_dist: float = 50.0
) -> tuple[int, np.ndarray]:
    """Identity switches of tracks against the truth (the multi-object tracking count).

    Per frame tracks and true animals are matched (Hungarian on distance, pairs within
    ``max_dist``); a match counts only where it is unambiguous: the track is at most half as
    far from its animal as from any other (a hypothesis between two animals in contact
    belongs to neither). A switch is a true animal matched to another track than the last
    track it was matched to.

    Args:
        track_centers: (T, A, 3) tracked centres, NaN where unmatched.
        true_centers: (T, B, 3) true centres, NaN where the animal is absent.
        max_dist: farthest match, mm.

    Returns:
        ``(switches, assigned)``: the count and (T, B) int64 the track matched to each
        true animal per frame (-1: none).
    """
    tx = np.asarray(track_centers, dtype=np.float64)
    gx = np.asarray(true_centers, dtype=np.float64)
    if tx.ndim != 3 or gx.ndim != 3 or len(tx) != len(gx):
        raise TrackingError(
            f"track_centers (T, A, 3) and true_centers (T, B, 3) must share T, got "
            f"{tx.shape} and {gx.shape}"
        )
    assigned = np.full(gx.shape[:2], -1, dtype=np.int64)
    for t in range(len(tx)):
        d = np.linalg.norm(tx[t][:, None] - gx[t][None], axis=-1)  # (A, B)
        d = np.where(np.isfinite(d), d, FORBIDDEN)
        second = np.sort(d, axis=1)[:, 1] if d.shape[1] > 1 else np.full(len(d), FORBIDDEN)
        rows, cols = linear_sum_assignment(np.where(d <= max_dist, d, FORBIDDEN))
        for r, b in zip(rows, cols, strict=True):
            if d[r, b] > max_dist or 2 * d[r, b] > second[r]:
                continue
            assigned[t, b] = r
    return len(switch_events(assigned)), assigned


def switch_events(assigned: np.ndarray) -> np.ndarray:
    """The identity switches of :func:`identity_switches`, one row each.

    Args:
        assigned: (T, B) the track matched to each true animal per frame, -1 none.

    Returns:
        (n, 5) int64 rows ``(animal, last frame on the old track, frame of the switch,
        old track, new track)``: consecutive matches of an animal to different tracks.
    """
    rows = []
    for b in range(assigned.shape[1]):
        seen = np.flatnonzero(assigned[:, b] >= 0)
        for t0, t1 in zip(seen[:-1], seen[1:], strict=True):
            if assigned[t0, b] != assigned[t1, b]:
                rows.append((b, t0, t1, assigned[t0, b], assigned[t1, b]))
    return np.asarray(rows, dtype=np.int64).reshape(-1, 5)


def lasting_switches(assigned: np.ndarray, min_frames: int) -> int:
    """Identity switches after which the animal stays with its new track.

    A track that strays onto the other animal of a contact for a few frames and comes back
    makes two switches of :func:`identity_switches` (there and back), yet every animal
    keeps its track. Here each animal's runs of matches to one track (from its first to
    its last frame, unmatched frames inside a run allowed) shorter than ``min_frames`` are
    dropped, neighbouring runs of the same track joined, and the changes of track between
    the remaining runs counted: a swap that lasts.

    Args:
        assigned: (T, B) the track matched to each true animal per frame, -1 none.
        min_frames: shortest run that counts (e.g. one second of frames).

    Returns:
        The count.
    """
    count = 0
    for b in range(assigned.shape[1]):
        seen = np.flatnonzero(assigned[:, b] >= 0)
        runs: list[list[int]] = []  # [track, first frame, last frame]
        for t in seen:
            k = int(assigned[t, b])
            if runs and runs[-1][0] == k:
                runs[-1][2] = int(t)
            else:
                runs.append([k, int(t), int(t)])
        kept = [r[0] for r in runs if r[2] - r[1] + 1 >= min_frames]
        count += sum(1 for old, new in zip(kept[:-1], kept[1:], strict=True) if old != new)
    return count


def identity_accuracy(assigned: np.ndarray, n_tracks: int) -> float:
    """Share of the matched animal-frames in which the animal is on its own track.

    Tracks and animals are paired one to one so that this share is largest (each
    animal's own track); a frame where the animal is matched to another track counts
    against it, however short the stray (the identity precision of the IDF1 score, over
    the frames where the animal is matched to some track).

    Args:
        assigned: (T, B) the track matched to each true animal per frame, -1 none.
        n_tracks: A, the number of tracks.

    Returns:
        The share in [0, 1]; NaN when no animal is ever matched.
    """
    counts = np.zeros((assigned.shape[1], max(n_tracks, 1)))
    for b in range(assigned.shape[1]):
        k = assigned[:, b]
        np.add.at(counts[b], k[k >= 0], 1)
    total = counts.sum()
    if total == 0:
        return float("nan")
    rows, cols = linear_sum_assignment(-counts)
    return float(counts[rows, cols].sum() / total)
