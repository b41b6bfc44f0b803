"""Synchronized decoding of all camera streams in background threads, ahead of the network.

One thread per camera decodes frames sequentially (OpenCV releases the GIL while it
decodes) into a bounded queue; the consumer assembles batches of synchronized frames. A
frame that cannot be decoded (a truncated or damaged file) ends that camera's stream: it
and every later frame of that camera are reported as missing, never silently dropped.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from freipose.io.video import MediaError

log = logging.getLogger(__name__)

_END = object()


@dataclass(frozen=True, eq=False)
class FrameBatch:
    """Synchronized frames of B time steps from C cameras.

    Attributes:
        frame_index: (B,) int64 video frame numbers.
        images: C arrays (B, H_c, W_c, 3) uint8 BGR; a missing frame is all zeros.
        valid: (B, C) bool, False where the camera's frame could not be decoded.
    """

    frame_index: np.ndarray
    images: list[np.ndarray]
    valid: np.ndarray

    def __len__(self) -> int:
        return len(self.frame_index)


def open_capture(path: Path, start: int) -> cv2.VideoCapture:
    """An OpenCV capture positioned so that the next ``read`` returns frame ``start``."""
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise MediaError(f"{path}: OpenCV cannot open this file as a video")
    if start > 0:
        cap.set(cv2.CAP_PROP_POS_FRAMES, start)
        pos = int(round(cap.get(cv2.CAP_PROP_POS_FRAMES)))
        if pos != start:  # inexact seek: fall back to decoding from the start
            log.debug("%s: seek to %d landed at %d; skipping frames instead", path, start, pos)
            cap.release()
            cap = cv2.VideoCapture(str(path))
            for _ in range(start):
                if not cap.grab():
                    break
    return cap


class SyncReader:
    """Iterate over batches of synchronized frames ``start <= i < stop`` of several videos.

    Args:
        videos: one video per camera (C).
        start, stop: frame range.
        batch_size: time steps per batch; batches are aligned so that every batch but the
            first starts at ``align + k * batch_size``.
        align: frame number batch boundaries are aligned to (default ``start``).
        prefetch: how many batches each camera may decode ahead.
        shapes: (H, W) per camera, used for the all-zero image of a missing frame.

    Use as a context manager (or call :meth:`close`) so that the threads stop.
    After iteration, :attr:`first_missing` maps a camera index to its first frame that
    could not be decoded.
    """

    def __init__(
        self,
        videos: Sequence[str | Path],
        start: int,
        stop: int,
        batch_size: int,
        shapes: Sequence[tuple[int, int]],
        align: int | None = None,
        prefetch: int = 3,
    ):
        if batch_size < 1:
            raise ValueError(f"batch size must be at least 1, got {batch_size}")
        if stop < start:
            raise ValueError(f"empty frame range {start}:{stop}")
        self.videos = [Path(v) for v in videos]
        self.start, self.stop = int(start), int(stop)
        self.batch_size = int(batch_size)
        self.shapes = [tuple(int(x) for x in s) for s in shapes]
        self.align = self.start if align is None else int(align)
        self.first_missing: dict[int, int] = {}
        self._stop_event = threading.Event()
        self._queues: list[queue.Queue] = [
            queue.Queue(maxsize=max(2, prefetch * self.batch_size)) for _ in self.videos
        ]
        self._threads = [
            threading.Thread(target=self._decode, args=(c,), daemon=True, name=f"decode-{c}")
            for c in range(len(self.videos))
        ]
        self._started = False

    # -- producer -------------------------------------------------------------------------
    def _put(self, c: int, item: object) -> bool:
        while not self._stop_event.is_set():
            try:
                self._queues[c].put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _decode(self, c: int) -> None:
        path = self.videos[c]
        cap = None
        try:
            cap = open_capture(path, self.start)
            ok_stream = True
            for i in range(self.start, self.stop):
                frame = None
                if ok_stream:
                    ok, frame = cap.read()
                    if not ok or frame is None:
                        ok_stream = False
                        frame = None
                        self.first_missing[c] = i
                    elif frame.shape[:2] != self.shapes[c]:
                        raise MediaError(
                            f"{path}: frame {i} is {frame.shape[1]}x{frame.shape[0]}, expected "
                            f"{self.shapes[c][1]}x{self.shapes[c][0]}"
                        )
                if not self._put(c, frame):
                    return
        except BaseException as exc:  # hand the error to the consumer
            self._put(c, exc)
            return
        finally:
            if cap is not None:
                cap.release()
        self._put(c, _END)

    # -- consumer -------------------------------------------------------------------------
    def _get(self, c: int) -> np.ndarray | None:
        item = self._queues[c].get()
        if isinstance(item, BaseException):
            raise item
        if item is _END:
            raise RuntimeError(f"{self.videos[c]}: decoder thread ended early")
        return item  # type: ignore[return-value]

    def batch_bounds(self) -> list[tuple[int, int]]:
        """The (first, stop) frame numbers of the batches, in order."""
        out = []
        i = self.start
        while i < self.stop:
            k = (i - self.align) // self.batch_size + 1
            j = min(self.align + k * self.batch_size, self.stop)
            out.append((i, j))
            i = j
        return out

    def __iter__(self) -> Iterator[FrameBatch]:
        if not self._started:
            self._started = True
            for t in self._threads:
                t.start()
        C = len(self.videos)
        for a, b in self.batch_bounds():
            n = b - a
            images = [np.zeros((n, h, w, 3), np.uint8) for h, w in self.shapes]
            valid = np.zeros((n, C), bool)
            for c in range(C):
                for r in range(n):
                    f = self._get(c)
                    if f is not None:
                        images[c][r] = f
                        valid[r, c] = True
            yield FrameBatch(np.arange(a, b, dtype=np.int64), images, valid)

    def close(self) -> None:
        """Stop the decoding threads and wait for them (up to 5 s each)."""
        self._stop_event.set()
        for t in self._threads:
            if t.is_alive():
                t.join(timeout=5)

    def __enter__(self) -> SyncReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
