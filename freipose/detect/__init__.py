"""Bounding boxes of the animal that are consistent across views.

* :mod:`.model`, :mod:`.detector`: a MobileNetV2-style, CenterNet-style single-class
  detector in plain PyTorch (:class:`Detector`, ``Detector.load(path, device)``);
* :mod:`.fallback`: :class:`BackgroundSubtractor` (static cameras, one animal) and
  :class:`FixedBoxes` (a TOML file), which need no training;
* :mod:`.multiview`: robust 3D centre from candidate boxes of all views, consistent boxes
  and cube crops (:func:`detect_multiview`, :func:`detect_multiview_batch`,
  :func:`consistent_detection` -> :class:`MultiViewDetection`, several instants at once
  with :func:`consistent_detections`);
* :mod:`.multi`: several animals: one box per animal per view (:class:`~.multi.SplitForeground`
  splits touching animals in the foreground, :class:`~.multi.PeakBoxes` keeps several
  detector peaks) and 3D animal hypotheses with a box in every view
  (:func:`~.multi.detect_animals` -> :class:`~.multi.AnimalDetections`);
* :mod:`.train`: ``train_detector`` for ``freipose train CONFIG --stage detector``;
* :mod:`.evaluate`: ground-truth boxes and metrics (recall, 3D centre error, fps);
* :mod:`.pipeline`: a box source over a whole session (``freipose detect``; the session
  itself is opened by :mod:`freipose.io.session`).

Every box source has ``propose(images, cameras) -> list[Candidates]``.
"""

from freipose.detect.base import BoxSource, Candidates
from freipose.detect.detector import Detector
from freipose.detect.fallback import BackgroundSubtractor, FixedBoxes
from freipose.detect.multiview import (
    ConsistencyConfig,
    MultiViewDetection,
    consistent_detection,
    consistent_detections,
    detect_multiview,
    detect_multiview_batch,
)

__all__ = [
    "BackgroundSubtractor",
    "BoxSource",
    "Candidates",
    "ConsistencyConfig",
    "Detector",
    "FixedBoxes",
    "MultiViewDetection",
    "consistent_detection",
    "consistent_detections",
    "detect_multiview",
    "detect_multiview_batch",
]
