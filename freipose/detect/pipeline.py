"""Running a box source over a whole session (what ``freipose detect`` does)."""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from freipose.detect.base import BoxSource, DetectConfigError
from freipose.detect.multiview import ConsistencyConfig, detect_multiview_batch
from freipose.geometry import CameraRig
from freipose.io.atomic import atomic_path
from freipose.io.boxes import BoxesData
from freipose.io.session import Session
from freipose.io.video import FrameSource, MediaError
from freipose.progress import progress_bar

log = logging.getLogger(__name__)


def open_sources(session: Session) -> dict[str, FrameSource]:
    """A frame source per camera of ``session``, in its camera order (the caller closes them).

    Args:
        session: a session opened with ``cameras="calibration"`` (see
            :func:`freipose.io.session.discover_sessions`).

    Returns:
        Camera name -> open frame source.
    """
    return {n: FrameSource(p) for n, p in session.videos.items()}


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
            raise DetectConfigError("give either --model or --fixed-boxes, not both")
        method = "detector" if model is not None else "fixed" if fixed_boxes is not None else None
        if method is None:
            raise DetectConfigError(
                "say how to find the animal: --model CKPT (trained detector), --method bgsub "
                "(background subtraction) or --fixed-boxes FILE"
            )
    if method == "detector":
        if model is None:
            raise DetectConfigError("--method detector needs --model CKPT")
        from freipose.detect.detector import Detector

        return Detector.load(model, device), "detector", str(model)
    if method == "fixed":
        if fixed_boxes is None:
            raise DetectConfigError("--method fixed needs --fixed-boxes FILE")
        from freipose.detect.fallback import FixedBoxes

        fb = FixedBoxes.from_toml(fixed_boxes)
        fb.check_cameras(rig.names)
        return fb, "fixed", str(fixed_boxes)
    if method == "bgsub":
        from freipose.detect.fallback import BackgroundSubtractor

        bg = BackgroundSubtractor.fit(dict(sources), n_samples=bg_samples, frames=frames)
        return bg, "bgsub", f"median background of {bg_samples} frames"
    raise DetectConfigError(f"unknown method {method!r}; use detector, bgsub or fixed")


def detect_session(
    rig: CameraRig,
    sources: Mapping[str, FrameSource],
    frames: range,
    source: BoxSource,
    config: ConsistencyConfig | None = None,
    batch_size: int = 8,
    method: str = "",
    source_desc: str = "",
    progress_file: Path | None = None,
    save_every: int = 500,
) -> BoxesData:
    """Consistent boxes for ``frames`` of a session (frames are read in order).

    With ``progress_file``, the results so far are saved there (atomically, every
    ``save_every`` frames); a later call with the same session, frames and settings
    continues from it. The caller removes it once the output is written.
    """
    cfg = config or ConsistencyConfig()
    t, c = len(frames), len(rig)
    arrays = {
        "boxes": np.full((t, c, 4), np.nan),
        "scores": np.full((t, c), np.nan, np.float32),
        "agree": np.zeros((t, c), bool),
        "n_agree": np.zeros(t, np.int16),
        "center": np.full((t, 3), np.nan),
        "crop_boxes": np.full((t, c, 4), np.nan),
    }
    signature = json.dumps(
        {
            "cameras": list(rig.names),
            "frames": [frames.start, frames.stop, frames.step],
            "method": method,
            "source": source_desc,
            "config": dataclasses.asdict(cfg),
        },
        sort_keys=True,
    )
    done = 0
    if progress_file is not None and Path(progress_file).is_file():
        done = _load_progress(Path(progress_file), signature, arrays)
        if done:
            log.info("resuming from %s: %d of %d frames done", progress_file, done, t)
    bar = progress_bar(total=t, initial=done, desc="detect", unit="frame", disable=None)
    last_save = done
    first_missing: dict[str, int] = {}
    for b0 in range(done, t, batch_size):
        idx = list(frames[b0 : b0 + batch_size])
        batch, valid = _read_batch(rig, sources, idx, first_missing)
        ok = None if valid.all() else valid
        for k, det in enumerate(detect_multiview_batch(batch, rig, source, cfg, ok)):
            j = b0 + k
            arrays["boxes"][j], arrays["scores"][j] = det.boxes, det.scores
            arrays["agree"][j], arrays["n_agree"][j] = det.agree, det.n_agree
            arrays["center"][j], arrays["crop_boxes"][j] = det.center, det.crop_boxes
            for key in ("boxes", "scores", "crop_boxes"):  # no box where no frame
                arrays[key][j][~valid[k]] = np.nan
        bar.update(len(idx))
        n_done = b0 + len(idx)
        if progress_file is not None and n_done - last_save >= save_every and n_done < t:
            _save_progress(Path(progress_file), signature, arrays, n_done)
            last_save = n_done
    bar.close()
    return BoxesData(
        frame_index=np.asarray(frames, dtype=np.int64),
        cameras=tuple(rig.names),
        cube_size=cfg.cube_size,
        method=method,
        calibration=rig,
        attrs={
            "source": source_desc,
            "min_views": cfg.min_views,
            "image_size": np.array([cam.size for cam in rig], dtype=np.int64),
        },
        **arrays,
    )


def _read_batch(
    rig: CameraRig,
    sources: Mapping[str, FrameSource],
    idx: list[int],
    first_missing: dict[str, int],
) -> tuple[list[list[np.ndarray]], np.ndarray]:
    """The frames ``idx`` of every camera and which could be decoded, ``(T, C)`` bool.

    A frame that cannot be decoded (a truncated or damaged video) ends that camera's
    video: ``first_missing`` records it and later frames of that camera are not read. A
    missing frame is a black image that no box source sees.
    """
    valid = np.ones((len(idx), len(rig)), bool)
    batch: list[list[np.ndarray]] = []
    for k, i in enumerate(idx):
        views = []
        for c, cam in enumerate(rig):
            img = None
            if i < first_missing.get(cam.name, i + 1):
                try:
                    img = sources[cam.name].read(i)
                except MediaError:
                    first_missing[cam.name] = i
                    log.warning(
                        "camera %r: frames from %d on cannot be decoded (truncated or damaged "
                        "video?); they get no box",
                        cam.name,
                        i,
                    )
            if img is None:
                valid[k, c] = False
                img = np.zeros((cam.height, cam.width, 3), np.uint8)
            views.append(img)
        batch.append(views)
    return batch, valid


def _save_progress(path: Path, signature: str, arrays: dict, done: int) -> None:
    with atomic_path(path, suffix=".npz") as tmp, open(tmp, "wb") as fh:
        np.savez(fh, signature=np.array(signature), done=np.array(done), **arrays)


def _load_progress(path: Path, signature: str, arrays: dict) -> int:
    """Fill ``arrays`` from a progress file made with the same settings; frames done (or 0)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["signature"]) != signature:
                log.warning("%s was made with other settings; starting over", path)
                return 0
            for k, a in arrays.items():
                if z[k].shape != a.shape:
                    return 0
                a[...] = z[k]
            return int(z["done"])
    except (OSError, KeyError, ValueError) as exc:
        log.warning("cannot read %s (%s); starting over", path, exc)
        return 0
