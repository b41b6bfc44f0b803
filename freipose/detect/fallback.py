"""Box sources that need no training: background subtraction and fixed boxes.

* :class:`BackgroundSubtractor` for static cameras and one animal: the background of each
  camera is the per-pixel median of frames sampled over the recording; a frame's
  foreground is where it differs from the background by more than a threshold, cleaned
  by morphology; the largest blobs become the candidates (score = blob area / largest
  blob area). It fails when the animal rests in one place for most of the sampled
  frames (it becomes background) or when the lighting changes.
* :class:`FixedBoxes`: the same box in every frame per camera, read from a TOML file::

      [boxes]
      cam0 = [100, 80, 500, 400]     # x0, y0, x1, y1 in pixels
      cam1 = [120, 60, 520, 380]
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path

import cv2
import numpy as np

from freipose._compat import tomllib
from freipose.detect.base import Candidates

log = logging.getLogger(__name__)


class BackgroundSubtractor:
    """Median-background foreground detector (a :class:`~freipose.detect.base.BoxSource`).

    Args:
        backgrounds: camera name -> background BGR uint8 image (full resolution).
        threshold: grey-level difference that counts as foreground; None picks it per
            image from the difference statistics (median + 6 x MAD, at least 20).
        min_area: smallest blob, as a fraction of the image area.
        margin: added on every side of a blob's box, as a fraction of its longer side.
        work_size: longest side of the images the subtraction runs on (speed).
        top_k: most candidates per image.
    """

    def __init__(
        self,
        backgrounds: Mapping[str, np.ndarray],
        threshold: float | None = None,
        min_area: float = 2e-4,
        margin: float = 0.0,
        work_size: int = 480,
        top_k: int = 3,
    ):
        if not backgrounds:
            raise ValueError("BackgroundSubtractor needs at least one camera's background")
        self.threshold = threshold
        self.min_area = min_area
        self.margin = margin
        self.work_size = work_size
        self.top_k = top_k
        self._bg = {name: self._prep(np.asarray(b))[0] for name, b in backgrounds.items()}
        self._full_size = {name: (b.shape[1], b.shape[0]) for name, b in backgrounds.items()}

    @classmethod
    def fit(
        cls,
        sources: Mapping[str, object],
        n_samples: int = 40,
        frames: range | None = None,
        **kwargs,
    ) -> BackgroundSubtractor:
        """Estimate the backgrounds from ``n_samples`` frames spread over each source.

        Args:
            sources: camera name -> anything with ``read(i)`` and ``num_frames`` (a
                :class:`freipose.io.video.FrameSource`) or a sequence of images.
            n_samples: frames per camera for the median.
            frames: restrict the sampling to these frame indices.
        """
        bgs = {}
        for name, src in sources.items():
            n = src.num_frames if hasattr(src, "num_frames") else len(src)  # type: ignore[arg-type]
            rng = frames if frames is not None else range(n)
            rng = range(max(rng.start, 0), min(rng.stop, n), rng.step)
            if len(rng) == 0:
                raise ValueError(f"camera {name}: no frames to estimate the background from")
            idx = np.unique(
                np.linspace(0, len(rng) - 1, min(n_samples, len(rng))).round().astype(int)
            )
            read = src.read if hasattr(src, "read") else src.__getitem__  # type: ignore[union-attr]
            stack = np.stack([np.asarray(read(rng[i])) for i in idx])
            bgs[name] = np.median(stack, axis=0).astype(np.uint8)
            log.info("background of %s from %d frames", name, len(idx))
        return cls(bgs, **kwargs)

    def _prep(self, img: np.ndarray) -> tuple[np.ndarray, float]:
        if img.ndim == 3:
            img = img.astype(np.float32)
        else:
            img = img.astype(np.float32)[..., None]
        h, w = img.shape[:2]
        s = min(1.0, self.work_size / max(h, w))
        if s < 1:
            img = cv2.resize(img, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
            if img.ndim == 2:
                img = img[..., None]
        return img, s

    def foreground(self, image: np.ndarray, camera: str) -> tuple[np.ndarray, float]:
        """The foreground mask (uint8 0/255, work size) of ``image`` and its scale factor."""
        if camera not in self._bg:
            raise KeyError(f"no background for camera {camera!r}; have {sorted(self._bg)}")
        img, s = self._prep(np.asarray(image))
        bg = self._bg[camera]
        if img.shape != bg.shape:
            raise ValueError(
                f"camera {camera}: image of shape {np.asarray(image).shape} does not match the "
                f"background's size {self._full_size[camera]}"
            )
        diff = np.abs(img - bg).max(-1)
        # A median filter removes pixel noise without growing the foreground's outline.
        diff = cv2.medianBlur(np.clip(diff, 0, 255).astype(np.uint8), 5).astype(np.float32)
        thr = self.threshold
        if thr is None:
            med = float(np.median(diff))
            mad = float(np.median(np.abs(diff - med)))
            thr = max(20.0, med + 6 * 1.4826 * mad)
        mask = (diff > thr).astype(np.uint8) * 255
        k = np.ones((3, 3), np.uint8)
        mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, k)
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))
        return mask, s

    def propose(self, images: Sequence[np.ndarray], cameras: Sequence[str]) -> list[Candidates]:
        """The largest foreground blobs per image as candidate boxes (full-image pixels)."""
        if len(images) != len(cameras):
            raise ValueError(f"{len(images)} images but {len(cameras)} camera names")
        out = []
        for img, cam in zip(images, cameras):
            mask, s = self.foreground(img, cam)
            n, _, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
            area = stats[1:, cv2.CC_STAT_AREA].astype(np.float64)
            keep = np.flatnonzero(area >= self.min_area * mask.size)
            keep = keep[np.argsort(-area[keep])][: self.top_k]
            if len(keep) == 0:
                out.append(Candidates.empty())
                continue
            st = stats[1:][keep].astype(np.float64)
            x0, y0 = st[:, 0] - 0.5, st[:, 1] - 0.5  # pixel edges at work scale
            x1, y1 = x0 + st[:, 2], y0 + st[:, 3]
            pad = self.margin * np.maximum(st[:, 2], st[:, 3])
            b = np.stack([x0 - pad, y0 - pad, x1 + pad, y1 + pad], -1)
            b = (b + 0.5) / s - 0.5  # back to full-image pixels
            out.append(Candidates(b, area[keep] / area[keep].max()))
        return out


class FixedBoxes:
    """The same box in every frame per camera (a :class:`~freipose.detect.base.BoxSource`).

    Args:
        boxes: camera name -> (x0, y0, x1, y1) full-image pixels.
    """

    def __init__(self, boxes: Mapping[str, Sequence[float]]):
        self.boxes: dict[str, np.ndarray] = {}
        for name, b in boxes.items():
            arr = np.asarray(b, dtype=np.float64)
            if (
                arr.shape != (4,)
                or not np.isfinite(arr).all()
                or arr[2] <= arr[0]
                or arr[3] <= arr[1]
            ):
                raise ValueError(
                    f"fixed box of camera {name!r} must be [x0, y0, x1, y1] with x1 > x0 and "
                    f"y1 > y0, got {b!r}"
                )
            self.boxes[str(name)] = arr

    @classmethod
    def from_toml(cls, path: str | Path) -> FixedBoxes:
        """Read ``[boxes] camera = [x0, y0, x1, y1]`` from a TOML file."""
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"{p}: fixed-boxes file not found")
        try:
            data = tomllib.loads(p.read_text())
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise ValueError(f"{p}: not valid TOML ({exc})") from exc
        boxes = data.get("boxes")
        if not isinstance(boxes, dict) or not boxes:
            raise ValueError(
                f"{p}: expected a [boxes] table with one `camera = [x0, y0, x1, y1]` entry "
                "per camera"
            )
        try:
            return cls(boxes)
        except ValueError as exc:
            raise ValueError(f"{p}: {exc}") from exc

    def propose(self, images: Sequence[np.ndarray], cameras: Sequence[str]) -> list[Candidates]:
        """The camera's fixed box with score 1 (no box for cameras not in the file)."""
        out = []
        for cam in cameras:
            b = self.boxes.get(str(cam))
            out.append(Candidates.empty() if b is None else Candidates(b[None], np.ones(1)))
        return out

    def check_cameras(self, cameras: Sequence[str]) -> None:
        """Raise ValueError when the file names no camera of ``cameras``."""
        if not set(self.boxes) & set(cameras):
            raise ValueError(
                f"the fixed boxes name cameras {sorted(self.boxes)}, none of the session's "
                f"{list(cameras)}"
            )
