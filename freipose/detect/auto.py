"""Choosing how to find the animal when the user did not say (``--method auto``).

In order, the first box source that finds the animal (a 3D centre agreed by
``min_views`` views) in at least ``min_share`` (80 %) of ``probe`` frames spread over the
run is used (one that misses it more often loses it for long stretches): the trained
detector (when one is given), background subtraction, and fixed boxes derived from the
training labels (:mod:`freipose.detect.label_boxes`), which need no
motion and no training. The choice and the reason are logged, e.g. ``using fixed boxes
from the labels: no detector given (--detector); background subtraction found the
animal in 7 of 40 sampled frames``. When none works and there are no labels, the best
source is used with a warning. Fixed boxes, and a source used although it did not find the
animal, propose nothing on blank frames (:class:`~freipose.detect.fallback.SkipBlank`:
black or one-coloured), so such frames are reported as not found rather than given a pose;
sampled frames blank in every camera are said in a warning.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from freipose.detect.multiview import ConsistencyConfig, detect_multiview_batch
from freipose.geometry import CameraRig
from freipose.io.video import MediaError

log = logging.getLogger(__name__)

PROBE = 40
MIN_SHARE = 0.8


@dataclass(frozen=True)
class AutoChoice:
    """The box source chosen and why.

    Attributes:
        source: the box source (``propose(images, cameras)``).
        method: ``detector``, ``bgsub`` or ``fixed``.
        reason: one sentence for the log: what was tried and what it found.
    """

    source: Any
    method: str
    reason: str


def _probe_frames(sources: Mapping[str, Any], frames: range, n: int) -> list[list[np.ndarray]]:
    """Up to ``n`` time instants spread over ``frames`` that decode in every camera."""
    idx = np.unique(np.linspace(0, len(frames) - 1, min(n, len(frames))).round().astype(int))
    out = []
    for i in idx:
        try:
            out.append([np.asarray(src.read(frames[int(i)])) for src in sources.values()])
        except (MediaError, IndexError):
            continue
    return out


def found_share(source: Any, probe: list[list[np.ndarray]], rig: CameraRig, min_views: int) -> int:
    """In how many probe instants ``source`` gives a 3D centre agreed by ``min_views`` views."""
    if not probe:
        return 0
    dets = detect_multiview_batch(probe, rig, source, ConsistencyConfig(min_views=min_views))
    return int(sum(bool(np.isfinite(d.center).all()) for d in dets))


def choose_box_source(
    rig: CameraRig,
    sources: Mapping[str, Any],
    frames: range,
    *,
    detector: Any = None,
    labels: Any = None,
    min_views: int = 2,
    bg_samples: int = 40,
    probe: int = PROBE,
    min_share: float = MIN_SHARE,
) -> AutoChoice:
    """The first box source that finds the animal (see the module docstring).

    Args:
        rig: the session's cameras (the order of ``sources``).
        sources: camera -> frame source (``read(i)``, ``num_frames``).
        frames: the run's frames.
        detector: a loaded detector, or None.
        labels: the training :class:`~freipose.io.labels.LabelSet` (for fixed boxes), or None.
        min_views: fewest agreeing views for a centre.
        bg_samples: frames for the background model.
        probe: frames to try each source on.
        min_share: share of the probe frames a source must find the animal in.

    Returns:
        The choice, with the reason (also logged).
    """
    from freipose.detect.fallback import (
        BackgroundSubtractor,
        FallbackBoxesError,
        FixedBoxes,
        SkipBlank,
        is_blank,
    )
    from freipose.detect.label_boxes import label_boxes

    shots = _probe_frames(sources, frames, probe)
    n = len(shots)
    blank = sum(all(is_blank(img) for img in shot) for shot in shots)
    if shots and blank == n:
        log.warning(
            "all %d sampled frames are blank in every camera (black or one colour: no "
            "light, lens cap, wrong videos?); frames without contrast are reported as "
            "not found",
            n,
        )
    tried: list[str] = []
    best: tuple[int, Any, str] | None = None
    if detector is None:
        tried.append("no detector given (--detector)")
    else:
        k = found_share(detector, shots, rig, min_views)
        msg = f"the detector found the animal in {k} of {n} sampled frames"
        if k >= min_share * n:
            return _chosen(detector, "detector", msg)
        tried.append(msg)
        best = (k, detector, "detector")
    bg = BackgroundSubtractor.fit(dict(sources), n_samples=bg_samples, frames=frames)
    k = found_share(bg, shots, rig, min_views)
    msg = f"background subtraction found the animal in {k} of {n} sampled frames"
    if k >= min_share * n:
        return _chosen(bg, "bgsub", "; ".join([*tried, msg]))
    tried.append(msg)
    if best is None or k > best[0]:
        best = (k, bg, "bgsub")
    if labels is not None:
        try:
            boxes = label_boxes(labels, rig)
        except FallbackBoxesError as exc:
            tried.append(f"no fixed boxes from the labels ({exc})")
        else:
            fixed = FixedBoxes(boxes.boxes, skip_blank=True)
            return _chosen(fixed, "fixed", "; ".join(tried), "fixed boxes from the labels")
    else:
        tried.append("no training labels to derive fixed boxes from")
    log.warning(
        "no way of finding the animal works well (%s); using %s. Train the detector "
        "(`freipose train CONFIG --stage detector`) or pass --fixed-boxes FILE "
        "(`freipose labels boxes`)",
        "; ".join(tried),
        best[2],
    )
    return AutoChoice(SkipBlank(best[1]), best[2], "; ".join(tried))


def _chosen(source: Any, method: str, reason: str, name: str | None = None) -> AutoChoice:
    names = {"detector": "the detector", "bgsub": "background subtraction"}
    log.info("using %s: %s", name or names[method], reason)
    return AutoChoice(source, method, reason)


def auto_box_source(
    session: Any,
    frames: tuple[int, int],
    detector_path: Path | None,
    labels_path: Path | None,
    min_views: int = 2,
    bg_samples: int = 40,
    device: str = "cpu",
) -> AutoChoice:
    """:func:`choose_box_source` for one session of ``freipose predict``.

    Args:
        session: a :class:`freipose.io.session.Session` (its rig and videos).
        frames: the run's frame range ``(start, stop)``.
        detector_path: a detector checkpoint, or None.
        labels_path: the training labels (``labels.h5``), or None.
        min_views: fewest agreeing views for a centre.
        bg_samples: frames for the background model.
        device: where the detector runs.

    Returns:
        The choice.
    """
    from freipose.io.labels import read_labels_h5
    from freipose.io.video import FrameSource

    detector = None
    if detector_path is not None:
        from freipose.detect.detector import Detector

        detector = Detector.load(detector_path, device)
    labels = None
    if labels_path is not None and Path(labels_path).is_file():
        labels = read_labels_h5(labels_path)
    elif labels_path is not None:
        log.warning("the training labels %s are not there: no fixed boxes from them", labels_path)
    sources = {c: FrameSource(p) for c, p in session.videos.items()}
    try:
        return choose_box_source(
            session.rig, sources, range(*frames), detector=detector, labels=labels,
            min_views=min_views, bg_samples=bg_samples,
        )  # fmt: skip
    finally:
        for s in sources.values():
            s.close()
