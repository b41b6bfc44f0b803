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

* :class:`SkipBlank` wraps a box source so that it proposes nothing on a blank image (no
  contrast: black, or one colour), where there is no animal to find (``FixedBoxes`` does
  the same with ``skip_blank``): fixed boxes would otherwise send an empty crop on to the
  pose network, which answers with a pose.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from freipose.detect.base import Candidates
from freipose.errors import FreiPoseError, InputFileError
from freipose.io.toml import read_toml
from freipose.io.video import MediaError

log = logging.getLogger(__name__)


class FallbackBoxesError(FreiPoseError):
    """Fixed boxes or a background model that do not fit the session (message says why)."""


class NoBackgroundError(FallbackBoxesError, KeyError):
    """A camera has no background model."""


def _decodable(name: str, read: Callable[[int], Any], indices: list[int]) -> list[np.ndarray]:
    """The frames ``indices`` that can be decoded (a truncated video lacks its last ones).

    Raises:
        FallbackBoxesError: none of them can be decoded.
    """
    out, bad = [], []
    for i in indices:
        try:
            out.append(np.asarray(read(i)))
        except MediaError:
            bad.append(i)
    if bad:
        log.warning(
            "camera %s: %d of the %d frames sampled for the background cannot be decoded "
            "(truncated or damaged video?); the background uses the other %d",
            name,
            len(bad),
            len(indices),
            len(out),
        )
    if not out:
        raise FallbackBoxesError(
            f"camera {name}: none of the {len(indices)} frames sampled for the background can "
            "be decoded; is the video damaged?"
        )
    return out


class BackgroundSubtractor:
    """Median-background foreground detector (a :class:`~freipose.detect.base.BoxSource`).

    Args:
        backgrounds: camera name -> background BGR uint8 image (full resolution).
        threshold: grey-level difference that counts as foreground; None picks it per
            image from the difference statistics (median + 6 x MAD, at least 20).
        min_area: smallest blob, as a fraction of the image area.
        margin: added on every side of a blob's box, as a fraction of its longer side
            (0.1, like the ground-truth boxes the detector is trained on).
        work_size: longest side of the images the subtraction runs on (speed).
        top_k: most candidates per image.
        merge_gap: blobs closer than this fraction of a group's longer side are merged
            (an animal whose colours partly match the background falls apart otherwise).
    """

    def __init__(
        self,
        backgrounds: Mapping[str, np.ndarray],
        threshold: float | None = None,
        min_area: float = 2e-4,
        margin: float = 0.1,
        work_size: int = 480,
        top_k: int = 3,
        merge_gap: float = 0.25,
    ):
        if not backgrounds:
            raise FallbackBoxesError("BackgroundSubtractor needs at least one camera's background")
        self.threshold = threshold
        self.min_area = min_area
        self.margin = margin
        self.work_size = work_size
        self.top_k = top_k
        self.merge_gap = merge_gap
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
            **kwargs: the subtractor's settings (see the class).

        Returns:
            The fitted subtractor.

        Raises:
            FallbackBoxesError: a camera has no frames in ``frames``.
        """
        bgs = {}
        for name, src in sources.items():
            n = src.num_frames if hasattr(src, "num_frames") else len(src)  # type: ignore[arg-type]
            rng = frames if frames is not None else range(n)
            rng = range(max(rng.start, 0), min(rng.stop, n), rng.step)
            if len(rng) == 0:
                raise FallbackBoxesError(
                    f"camera {name}: no frames to estimate the background from"
                )
            idx = np.unique(
                np.linspace(0, len(rng) - 1, min(n_samples, len(rng))).round().astype(int)
            )
            read = src.read if hasattr(src, "read") else src.__getitem__  # type: ignore[union-attr]
            stack = np.stack(_decodable(name, read, [rng[i] for i in idx]))
            bgs[name] = np.median(stack, axis=0).astype(np.uint8)
            log.info("background of %s from %d frames", name, len(stack))
        return cls(bgs, **kwargs)

    def _prep(self, img: np.ndarray) -> tuple[np.ndarray, float]:
        img = img.astype(np.float32) if img.ndim == 3 else img.astype(np.float32)[..., None]
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
            raise NoBackgroundError(f"no background for camera {camera!r}; have {sorted(self._bg)}")
        img, s = self._prep(np.asarray(image))
        bg = self._bg[camera]
        if img.shape != bg.shape:
            raise FallbackBoxesError(
                f"camera {camera}: image of shape {np.asarray(image).shape} does not match the "
                f"background's size {self._full_size[camera]}"
            )
        d = np.abs(img - bg)
        diff = d[..., 0]
        for c in range(1, d.shape[-1]):  # the largest difference over the channels
            diff = np.maximum(diff, d[..., c])
        # A median filter removes pixel noise without growing the foreground's outline.
        grey = cv2.medianBlur(np.clip(diff, 0, 255).astype(np.uint8), 5)
        diff = grey.astype(np.float32)
        thr = self.threshold
        if thr is None:
            thr = max(20.0, _median_and_mad(grey, 6 * 1.4826))
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
            _, _, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
            boxes, areas = _merged_blobs(stats[1:], self.min_area * mask.size, self.merge_gap)
            boxes, areas = boxes[: self.top_k], areas[: self.top_k]
            if len(boxes) == 0:
                out.append(Candidates.empty())
                continue
            side = np.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1])
            b = boxes + (self.margin * side)[:, None] * np.array([-1, -1, 1, 1])
            b = (b + 0.5) / s - 0.5  # back to full-image pixels
            out.append(Candidates(b, areas / areas.max()))
        return out


def _median_and_mad(grey: np.ndarray, k: float) -> float:
    """``median + k * MAD`` of a uint8 image, from its histogram.

    The same value as ``np.median`` of the grey levels and of their absolute deviations
    (both exact: the levels are integers, a median of an even count the mean of the two
    middle values).
    """
    counts = np.bincount(grey.ravel(), minlength=256)
    levels = np.arange(256, dtype=np.float64)
    med = _sorted_median(levels, counts)
    dev = np.abs(levels - med)
    order = np.argsort(dev, kind="stable")
    return med + k * _sorted_median(dev[order], counts[order])


def _sorted_median(values: np.ndarray, counts: np.ndarray) -> float:
    """The median of ``values`` (ascending) each repeated ``counts`` times."""
    cum = np.cumsum(counts)
    n = int(cum[-1])
    lo, hi = values[np.searchsorted(cum, [(n - 1) // 2 + 1, n // 2 + 1])]
    return float((lo + hi) / 2)


def _merged_blobs(stats: np.ndarray, min_area: float, gap: float) -> tuple[np.ndarray, np.ndarray]:
    """Group connected components into animals, largest first.

    An animal whose colours partly match the background falls apart into several blobs;
    starting from the largest blob, every blob (of at least a quarter of ``min_area``)
    whose box comes within ``gap`` x the group's longer side is merged in. Groups smaller
    than ``min_area`` are dropped. Returns boxes (n, 4) (pixel edges) and areas (n,).
    """
    st = np.asarray(stats, dtype=np.float64).reshape(-1, 5)
    area = st[:, cv2.CC_STAT_AREA]
    ok = area >= min_area / 4
    st, area = st[ok], area[ok]
    box = np.stack([st[:, 0] - 0.5, st[:, 1] - 0.5, st[:, 0] + st[:, 2] - 0.5,
                    st[:, 1] + st[:, 3] - 0.5], -1)  # fmt: skip
    free = np.ones(len(st), bool)
    groups, g_area = [], []
    for i in np.argsort(-area):
        if not free[i]:
            continue
        free[i] = False
        gb, ga = box[i].copy(), area[i]
        grew = True
        while grew:
            grew = False
            pad = gap * max(gb[2] - gb[0], gb[3] - gb[1])
            near = free & (box[:, 0] <= gb[2] + pad) & (box[:, 2] >= gb[0] - pad)
            near &= (box[:, 1] <= gb[3] + pad) & (box[:, 3] >= gb[1] - pad)
            if near.any():
                gb = np.concatenate([np.minimum(gb[:2], box[near, :2].min(0)),
                                     np.maximum(gb[2:], box[near, 2:].max(0))])  # fmt: skip
                ga += area[near].sum()
                free &= ~near
                grew = True
        if ga >= min_area:
            groups.append(gb)
            g_area.append(ga)
    order = np.argsort(-np.asarray(g_area)) if g_area else np.zeros(0, int)
    return np.asarray(groups).reshape(-1, 4)[order], np.asarray(g_area, dtype=np.float64)[order]


class FixedBoxes:
    """The same box in every frame per camera (a :class:`~freipose.detect.base.BoxSource`).

    Args:
        boxes: camera name -> (x0, y0, x1, y1) full-image pixels.
        skip_blank: propose no box on a blank image (:func:`is_blank`).
    """

    def __init__(self, boxes: Mapping[str, Sequence[float]], skip_blank: bool = False):
        self.skip_blank = skip_blank
        self.boxes: dict[str, np.ndarray] = {}
        for name, b in boxes.items():
            arr = np.asarray(b, dtype=np.float64)
            if (
                arr.shape != (4,)
                or not np.isfinite(arr).all()
                or arr[2] <= arr[0]
                or arr[3] <= arr[1]
            ):
                raise FallbackBoxesError(
                    f"fixed box of camera {name!r} must be [x0, y0, x1, y1] with x1 > x0 and "
                    f"y1 > y0, got {b!r}"
                )
            self.boxes[str(name)] = arr

    @classmethod
    def from_toml(cls, path: str | Path) -> FixedBoxes:
        """Read ``[boxes] camera = [x0, y0, x1, y1]`` from a TOML file.

        Args:
            path: the fixed-boxes file.

        Returns:
            The fixed boxes.

        Raises:
            InputFileError: no such file.
            FallbackBoxesError: not TOML, no ``[boxes]`` table, or a malformed box.
        """
        p = Path(path)
        if not p.is_file():
            raise InputFileError(f"{p}: fixed-boxes file not found")
        data = read_toml(p, "fixed-boxes file", FallbackBoxesError)
        boxes = data.get("boxes")
        if not isinstance(boxes, dict) or not boxes:
            raise FallbackBoxesError(
                f"{p}: expected a [boxes] table with one `camera = [x0, y0, x1, y1]` entry "
                "per camera"
            )
        try:
            return cls(boxes)
        except ValueError as exc:
            raise FallbackBoxesError(f"{p}: {exc}") from exc

    def propose(self, images: Sequence[np.ndarray], cameras: Sequence[str]) -> list[Candidates]:
        """The camera's fixed box with score 1.

        No box for cameras not in the file, nor, with ``skip_blank``, on a blank image.
        """
        out = []
        for i, cam in enumerate(cameras):
            b = self.boxes.get(str(cam))
            if b is None or (self.skip_blank and is_blank(images[i])):
                out.append(Candidates.empty())
            else:
                out.append(Candidates(b[None], np.ones(1)))
        return out

    def check_cameras(self, cameras: Sequence[str]) -> None:
        """Raise FallbackBoxesError when the file names no camera of ``cameras``."""
        if not set(self.boxes) & set(cameras):
            raise FallbackBoxesError(
                f"the fixed boxes name cameras {sorted(self.boxes)}, none of the session's "
                f"{list(cameras)}"
            )


# Grey-level standard deviation below which an image counts as blank (black, one colour):
# sensor noise alone gives more than this on a lit scene.
BLANK_STD = 2.0


def is_blank(image: np.ndarray, min_std: float = BLANK_STD) -> bool:
    """Whether ``image`` shows nothing: its grey levels vary by less than ``min_std``.

    Args:
        image: (H, W) or (H, W, 3) image.
        min_std: the standard deviation (grey levels) an image with content exceeds.

    Returns:
        True for a black or one-coloured image.
    """
    img = np.asarray(image)
    sub = img[::4, ::4].astype(np.float32)  # every 16th pixel: enough, and fast
    grey = sub.mean(axis=-1) if sub.ndim == 3 else sub
    return bool(grey.size == 0 or float(grey.std()) < min_std)


class SkipBlank:
    """A box source that proposes nothing on blank images, else what ``source`` proposes.

    Args:
        source: the box source (``propose(images, cameras)``).
        min_std: see :func:`is_blank`.
    """

    def __init__(self, source: Any, min_std: float = BLANK_STD):
        self.source = source
        self.min_std = min_std

    def propose(self, images: Sequence[np.ndarray], cameras: Sequence[str]) -> list[Candidates]:
        """The wrapped source's candidates, none for a blank image."""
        out = self.source.propose(images, cameras)
        return [
            Candidates.empty() if is_blank(img, self.min_std) else c
            for c, img in zip(out, images, strict=True)
        ]
