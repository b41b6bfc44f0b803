"""Several animals over a recording: detection, association, tracking, and how good they are.

:func:`track_recording` runs, chunk by chunk, a box source that gives several boxes per
view (:class:`freipose.detect.multi.SplitForeground`, :class:`~freipose.detect.multi.PeakBoxes`),
the association into 3D animal hypotheses (:func:`freipose.detect.multi.detect_animals`;
with a source that can split blobs at given centres, such as ``SplitForeground``, a
second look splits the blobs of animals in contact where the hypotheses project and is
kept where more views agree),
the coat colour of each hypothesis from its own boxes
(:func:`freipose.predict.tracking.colour_features`), and then the tracking
(:func:`freipose.predict.tracking.track_animals`).

:func:`score_tracks` compares the result with known 2D keypoints of every animal (a
synthetic scene's ``points2d`` and ``visible2d``): the true box of an animal in a view is
the box of its projected keypoints widened by 10 % (the detector's training rule,
:func:`freipose.detect.boxes.boxes_from_points`); its true centre the triangulation of the
true box centres; an animal is *visible* in a view when at least ``min_visible`` of its
keypoints are and at least half its box is inside the image. Recall counts the visible
(frame, view) pairs of an animal where a box (IoU >= 0.5) was found: among the view's
candidates (``recall_boxes``), and as the own box of the track that follows the animal
(``recall_tracked``).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from freipose.detect.base import BoxSource, Candidates
from freipose.detect.boxes import (
    box_centers,
    box_iou,
    boxes_from_points,
    clip_boxes,
    visible_fraction,
)
from freipose.detect.multi import AnimalDetections, AnimalsConfig, detect_animals
from freipose.geometry import CameraRig, project_rig, triangulate
from freipose.predict.tracking import (
    TrackingConfig,
    Tracks,
    colour_features,
    identity_accuracy,
    identity_switches,
    lasting_switches,
    switch_events,
    track_animals,
)

_NO_IMAGE = np.zeros((1, 1, 3), np.uint8)


@dataclass(frozen=True, eq=False)
class RecordingTracks:
    """The tracks of a recording and what they were made from.

    Attributes:
        tracks: the :class:`~freipose.predict.tracking.Tracks` (T frames, A animals).
        detections: (T,) the animal hypotheses per frame (empty: not kept).
        candidates: (T, C) the box source's candidates (empty: not kept).
        features: (T,) the hypotheses' coat features (H_t, F) (empty: not kept, or no
            appearance).
    """

    tracks: Tracks
    detections: tuple[AnimalDetections, ...]
    candidates: tuple[tuple[Candidates, ...], ...]
    features: tuple[np.ndarray, ...] = ()


def track_recording(
    frames: Iterable[Sequence[np.ndarray | None]],
    rig: CameraRig,
    source: BoxSource,
    n_animals: int,
    fps: float,
    config: AnimalsConfig | None = None,
    tracking: TrackingConfig | None = None,
    bounds: np.ndarray | None = None,
    appearance: bool = True,
    chunk: int = 32,
    keep: bool = True,
) -> RecordingTracks:
    """Detect, associate and track ``n_animals`` over a recording (module docstring).

    Args:
        frames: per time instant C BGR uint8 images (the rig's order); None for a camera
            whose frame could not be decoded (no boxes in that view).
        rig: the cameras.
        source: a box source giving several boxes per view.
        n_animals: how many animals.
        fps: frames per second.
        config: association settings (``max_animals`` defaults to ``n_animals + 1``).
        tracking: tracking settings.
        bounds: (3, 2) world box mm the animals' centres lie in (e.g. the arena).
        appearance: use the coat colours of the boxes in the tracking.
        chunk: time instants sent to ``source`` at once.
        keep: keep every frame's candidates, hypotheses and features in the result
            (False: the tracks only, ``detections``, ``candidates`` and ``features``
            empty: a long recording's prediction needs no more).

    Returns:
        :class:`RecordingTracks`.
    """
    cfg = config or AnimalsConfig(max_animals=n_animals + 1)
    names = list(rig.names)
    dets: list[AnimalDetections] = []
    cands: list[tuple[Candidates, ...]] = []
    centres: list[np.ndarray] = []
    boxes: list[np.ndarray] = []
    feats: list[np.ndarray] = []
    batch: list[Sequence[np.ndarray | None]] = []
    masker = getattr(source, "foreground_masks", None)  # the coats' pixels, where known
    reseed = getattr(source, "propose_seeded", None)  # blobs split at the hypotheses

    def flush() -> None:
        flat = [img for fr in batch for img in fr if img is not None]
        got = iter(
            source.propose(flat, [n for fr in batch for n, im in zip(names, fr) if im is not None])
        )
        for fr in batch:
            cd = tuple(Candidates.empty() if img is None else next(got) for img in fr)
            det = detect_animals(cd, rig, cfg, bounds)
            if reseed is not None and len(det):
                cd2, det2 = _resplit(reseed, fr, names, rig, det, cfg, bounds)
                if det2.n_views.sum() > det.n_views.sum():  # the views agree more
                    cd, det = cd2, det2
            centres.append(det.centers)
            boxes.append(det.boxes)
            if keep:
                cands.append(cd)
                dets.append(det)
            if appearance:  # a missing view has no own box: its image is never read
                shown = [_NO_IMAGE if img is None else img for img in fr]
                fg = None
                if masker is not None:
                    got_m = iter(
                        masker(
                            [im for im in fr if im is not None],
                            [n for n, im in zip(names, fr) if im is not None],
                        )
                    )
                    fg = [None if im is None else next(got_m) for im in fr]  # fmt: skip
                feats.append(colour_features(shown, det.boxes, det.own, masks=fg))
        batch.clear()

    for fr in frames:
        if len(fr) != len(names):
            raise ValueError(f"expected {len(names)} images ({names}), got {len(fr)}")
        batch.append(fr)
        if len(batch) >= chunk:
            flush()
    if batch:
        flush()
    tracks = track_animals(
        centres, n_animals, fps, features=feats if appearance else None, boxes=boxes,
        config=tracking,
    )  # fmt: skip
    return RecordingTracks(tracks, tuple(dets), tuple(cands), tuple(feats) if keep else ())


def _resplit(
    reseed: Any,
    frame: Sequence[np.ndarray | None],
    names: list[str],
    rig: CameraRig,
    det: AnimalDetections,
    cfg: AnimalsConfig,
    bounds: np.ndarray | None,
) -> tuple[tuple[Candidates, ...], AnimalDetections]:
    """Candidates and hypotheses again, blobs split at the hypotheses' projections.

    A second look at animals in contact: a view's blob of two animals is split along the
    line between where the first hypotheses project (the other views fix them), not
    where its outline narrows. :func:`track_recording` keeps it where more boxes agree
    with the hypotheses than at the first look.
    """
    uv = project_rig(det.centers[:, None, :], rig)[:, :, 0, :]  # (H, C, 2)
    shown = [c for c, im in enumerate(frame) if im is not None]
    got = iter(reseed([frame[c] for c in shown], [names[c] for c in shown],
                      [uv[:, c] for c in shown]))  # fmt: skip
    cd = tuple(Candidates.empty() if im is None else next(got) for im in frame)
    return cd, detect_animals(cd, rig, cfg, bounds)


@dataclass(frozen=True)
class TrackScores:
    """How well animals were detected and followed (see the module docstring).

    Attributes:
        switches: identity switches (:func:`~freipose.predict.tracking.identity_switches`).
        minutes: length of the recording.
        switches_per_minute: switches / minutes.
        recall_boxes: (A,) per animal, visible views with a candidate box at IoU >= 0.5.
        recall_tracked: (A,) per animal, visible views where its track's own box matches.
        followed: (A,) fraction of frames in which the animal is matched to a track.
        center_error_mm: median distance of matched tracks from the true centres.
        flagged_fraction: fraction of matched (frame, track) pairs flagged.
        n_visible: (A,) visible (frame, view) pairs per animal.
        switches_flagged: the switches where the tracker flagged one of the two tracks
            from ``flag_window`` frames before the animal was last matched to the frame of
            the switch (a user who checks the flagged frames finds these).
        lasting_switches: the switches after which the animal stays with the new track
            for at least ``lasting_s`` (:func:`~freipose.predict.tracking.lasting_switches`);
            the others are strays of a track onto another animal and back.
        identity_accuracy: share of the matched animal-frames in which the animal is on
            its own track (:func:`~freipose.predict.tracking.identity_accuracy`).
    """

    switches: int
    minutes: float
    switches_per_minute: float
    recall_boxes: tuple[float, ...]
    recall_tracked: tuple[float, ...]
    followed: tuple[float, ...]
    center_error_mm: float
    flagged_fraction: float
    n_visible: tuple[int, ...]
    switches_flagged: int
    lasting_switches: int
    identity_accuracy: float


def true_animal_boxes(points2d: np.ndarray, rig: CameraRig) -> tuple[np.ndarray, np.ndarray]:
    """True boxes (T, A, C, 4) from keypoints (T, A, C, K, 2), and true centres (T, A, 3)."""
    boxes = boxes_from_points(np.asarray(points2d, dtype=np.float64), margin=0.1)
    centres = triangulate(box_centers(boxes), rig)
    return boxes, centres


def score_tracks(
    result: RecordingTracks,
    points2d: np.ndarray,
    visible2d: np.ndarray,
    rig: CameraRig,
    min_visible: float = 0.5,
    max_dist: float = 60.0,
    flag_window: int = 5,
    lasting_s: float = 1.0,
) -> TrackScores:
    """Scores of a :class:`RecordingTracks` against known keypoints.

    Args:
        result: the tracks.
        points2d: (T, A, C, K, 2) true projections of every animal's keypoints.
        visible2d: (T, A, C, K) which are visible.
        rig: the cameras (C).
        min_visible: fraction of an animal's keypoints visible in a view for it to count.
        max_dist: farthest track from a true centre that still follows it, mm.
        flag_window: frames before a switch in which a flag counts for it.
        lasting_s: shortest time an animal stays with a new track for its switch to last.

    Returns:
        :class:`TrackScores`.
    """
    tr = result.tracks
    gt_boxes, gt_centres = true_animal_boxes(points2d, rig)
    t_n, a_n, c_n = gt_boxes.shape[:3]
    if len(result.detections) != t_n:
        raise ValueError(f"{len(result.detections)} frames tracked, {t_n} in the truth")
    sizes = [(int(c.size[0]), int(c.size[1])) for c in rig]
    clip = np.stack([clip_boxes(gt_boxes[:, :, c], sizes[c]) for c in range(c_n)], 2)
    inside = np.stack([visible_fraction(gt_boxes[:, :, c], sizes[c]) for c in range(c_n)], 2)
    shown = (np.asarray(visible2d).mean(-1) >= min_visible) & (np.nan_to_num(inside) >= 0.5)
    switches, assigned = identity_switches(tr.centers, gt_centres, max_dist)
    hit_box = np.zeros((t_n, a_n, c_n), bool)
    hit_track = np.zeros((t_n, a_n, c_n), bool)
    errs = []
    for t in range(t_n):
        for c in range(c_n):
            b = result.candidates[t][c].boxes
            if len(b):
                iou = np.nan_to_num(box_iou(b[:, None], clip[t, None, :, c]))  # (n, A)
                hit_box[t, :, c] = (iou >= 0.5).any(0)
        for a in range(a_n):
            k = assigned[t, a]
            if k < 0:
                continue
            errs.append(float(np.linalg.norm(tr.centers[t, k] - gt_centres[t, a])))
            h = tr.hypothesis[t, k]
            own = result.detections[t].own[h]
            iou = np.nan_to_num(box_iou(result.detections[t].boxes[h], clip[t, a]))
            hit_track[t, a] = own & (iou >= 0.5)
    n_vis = shown.sum((0, 2))
    minutes = t_n / tr.fps / 60.0
    matched = tr.observed
    return TrackScores(
        switches=int(switches),
        minutes=float(minutes),
        switches_per_minute=float(switches / minutes) if minutes > 0 else float("nan"),
        recall_boxes=tuple(float(v) for v in (hit_box & shown).sum((0, 2)) / np.maximum(n_vis, 1)),
        recall_tracked=tuple(
            float(v) for v in (hit_track & shown).sum((0, 2)) / np.maximum(n_vis, 1)
        ),
        followed=tuple(float(v) for v in (assigned >= 0).mean(0)),
        center_error_mm=float(np.median(errs)) if errs else float("nan"),
        flagged_fraction=float(tr.flagged[matched].mean()) if matched.any() else float("nan"),
        n_visible=tuple(int(v) for v in n_vis),
        switches_flagged=flagged_switches(assigned, tr.flagged, flag_window),
        lasting_switches=lasting_switches(assigned, max(int(round(lasting_s * tr.fps)), 1)),
        identity_accuracy=identity_accuracy(assigned, tr.num_animals),
    )


def flagged_switches(assigned: np.ndarray, flagged: np.ndarray, window: int) -> int:
    """Switches (:func:`~freipose.predict.tracking.switch_events`) with a flag on either track.

    Args:
        assigned: (T, B) the track matched to each true animal per frame, -1 none.
        flagged: (T, A) the tracks' flags.
        window: frames before the animal's last match in which a flag counts.
    """
    return sum(
        int(flagged[max(t0 - window, 0) : t1 + 1, [old, new]].any())
        for _, t0, t1, old, new in switch_events(assigned)
    )
