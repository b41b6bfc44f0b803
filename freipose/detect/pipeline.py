"""Running a box source over a whole session (what ``freipose detect`` does)."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from tqdm import tqdm

from freipose.detect.base import BoxSource
from freipose.detect.multiview import ConsistencyConfig, detect_multiview_batch
from freipose.geometry import CameraRig
from freipose.io.boxes import BoxesData
from freipose.io.calibration import load_calibration
from freipose.io.video import FrameSource, find_camera_videos

log = logging.getLogger(__name__)


def parse_frames(text: str | None, n_frames: int) -> range:
    """``START:STOP`` (either may be empty; Python slice rules, no step) -> a frame range."""
    if text is None:
        return range(n_frames)
    parts = str(text).split(":")
    if len(parts) != 2:
        raise ValueError(f"frames must be START:STOP (e.g. 0:1000 or 500:), got {text!r}")
    try:
        start = int(parts[0]) if parts[0].strip() else None
        stop = int(parts[1]) if parts[1].strip() else None
    except ValueError as exc:
        raise ValueError(f"frames must be START:STOP with integers, got {text!r}") from exc
    r = range(n_frames)[slice(start, stop)]
    if len(r) == 0:
        raise ValueError(f"frames {text} selects no frame of a video with {n_frames} frames")
    return r


def open_session(
    session: Path, calibration: Path | None = None
) -> tuple[CameraRig, dict[str, FrameSource], int]:
    """The calibrated cameras that have a video, their frame sources and the frame count.

    Args:
        session: a folder with one video per camera (file stem = camera name).
        calibration: the calibration file (default ``session/calibration.toml``).
    """
    session = Path(session)
    calib = Path(calibration) if calibration is not None else session / "calibration.toml"
    if not calib.is_file():
        raise FileNotFoundError(
            f"{calib}: calibration not found; pass --calibration FILE or put calibration.toml "
            f"in the session folder"
        )
    rig = load_calibration(calib)
    videos = find_camera_videos(session)
    names = [n for n in rig.names if n in videos]
    missing = [n for n in rig.names if n not in videos]
    if len(names) < 2:
        raise ValueError(
            f"{session}: videos {sorted(videos)} match only {names} of the calibrated cameras "
            f"{rig.names}; video file stems must be the camera names and at least two are needed"
        )
    if missing:
        log.warning("no video for calibrated cameras %s; using %s", missing, names)
    rig = rig.subset(names)
    sources = {n: FrameSource(videos[n]) for n in names}
    counts = {n: s.num_frames for n, s in sources.items()}
    n_frames = min(counts.values())
    if len(set(counts.values())) > 1:
        log.warning("videos differ in length %s; using the first %d frames", counts, n_frames)
    for n, cam in zip(names, rig):
        if tuple(sources[n].size) != tuple(cam.size):
            raise ValueError(
                f"{videos[n]}: frames are {sources[n].size[0]}x{sources[n].size[1]} but the "
                f"calibration says camera {n} is {cam.size[0]}x{cam.size[1]}; wrong calibration?"
            )
    return rig, sources, n_frames


def make_source(
    rig: CameraRig,
    sources: Mapping[str, FrameSource],
    frames: range,
    model: Path | None = None,
    method: str | None = None,
    fixed_boxes: Path | None = None,
    device: str = "auto",
    bg_samples: int = 40,
) -> tuple[BoxSource, str, str]:
    """The box source the options ask for: ``(source, method name, description)``."""
    if method is None:
        if model is not None and fixed_boxes is not None:
            raise ValueError("give either --model or --fixed-boxes, not both")
        method = "detector" if model is not None else "fixed" if fixed_boxes is not None else None
        if method is None:
            raise ValueError(
                "say how to find the animal: --model CKPT (trained detector), --method bgsub "
                "(background subtraction) or --fixed-boxes FILE"
            )
    if method == "detector":
        if model is None:
            raise ValueError("--method detector needs --model CKPT")
        from freipose.detect.detector import Detector

        return Detector.load(model, device), "detector", str(model)
    if method == "fixed":
        if fixed_boxes is None:
            raise ValueError("--method fixed needs --fixed-boxes FILE")
        from freipose.detect.fallback import FixedBoxes

        fb = FixedBoxes.from_toml(fixed_boxes)
        fb.check_cameras(rig.names)
        return fb, "fixed", str(fixed_boxes)
    if method == "bgsub":
        from freipose.detect.fallback import BackgroundSubtractor

        bg = BackgroundSubtractor.fit(dict(sources), n_samples=bg_samples, frames=frames)
        return bg, "bgsub", f"median background of {bg_samples} frames"
    raise ValueError(f"unknown method {method!r}; use detector, bgsub or fixed")


def detect_session(
    rig: CameraRig,
    sources: Mapping[str, FrameSource],
    frames: range,
    source: BoxSource,
    config: ConsistencyConfig | None = None,
    batch_size: int = 8,
    method: str = "",
    source_desc: str = "",
) -> BoxesData:
    """Consistent boxes for ``frames`` of a session (frames are read in order)."""
    cfg = config or ConsistencyConfig()
    t, c = len(frames), len(rig)
    boxes = np.full((t, c, 4), np.nan)
    scores = np.full((t, c), np.nan, np.float32)
    agree = np.zeros((t, c), bool)
    n_agree = np.zeros(t, np.int16)
    center = np.full((t, 3), np.nan)
    crops = np.full((t, c, 4), np.nan)
    bar = tqdm(total=t, desc="detect", unit="frame", disable=None)
    for b0 in range(0, t, batch_size):
        idx = list(frames[b0 : b0 + batch_size])
        batch = [[sources[n].read(i) for n in rig.names] for i in idx]
        for k, det in enumerate(detect_multiview_batch(batch, rig, source, cfg)):
            j = b0 + k
            boxes[j], scores[j], agree[j] = det.boxes, det.scores, det.agree
            n_agree[j], center[j], crops[j] = det.n_agree, det.center, det.crop_boxes
        bar.update(len(idx))
    bar.close()
    return BoxesData(
        frame_index=np.asarray(frames, dtype=np.int64),
        cameras=tuple(rig.names),
        boxes=boxes,
        scores=scores,
        agree=agree,
        n_agree=n_agree,
        center=center,
        crop_boxes=crops,
        cube_size=cfg.cube_size,
        method=method,
        calibration=rig,
        attrs={
            "source": source_desc,
            "min_views": cfg.min_views,
            "image_size": np.array([cam.size for cam in rig], dtype=np.int64),
        },
    )
