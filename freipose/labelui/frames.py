"""Frames of the labeled instants, decoded and JPEG-encoded on the server, prefetched.

A small least-recently-used cache holds the JPEG images of the last instants; a
background thread decodes the instants the page is likely to show next (the following
ones and the next least-confident one) while the user labels the current one.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections import OrderedDict
from collections.abc import Sequence

import cv2

from freipose.io.session import Session
from freipose.io.video import FrameSource
from freipose.labelui.store import Instant

log = logging.getLogger(__name__)


class FrameCache:
    """JPEG frames of instants, by (instant index, camera).

    Instants of one session and frame (several animals) share their images.

    Args:
        sessions: session name -> the session.
        instants: the instants (their indices are the keys).
        cache_instants: how many instants' images to keep.
        quality: JPEG quality (0-100).
    """

    def __init__(
        self,
        sessions: dict[str, Session],
        instants: Sequence[Instant],
        cache_instants: int = 16,
        quality: int = 85,
    ):
        self.sessions = sessions
        self.instants = instants
        self.quality = int(quality)
        self._max = max(1, cache_instants) * max(len(s.cameras) for s in sessions.values())
        self._cache: OrderedDict[tuple[str, int, str], bytes] = OrderedDict()
        self._cache_lock = threading.Lock()
        self._sources: dict[tuple[str, str], FrameSource] = {}
        self._source_locks: dict[tuple[str, str], threading.Lock] = {
            (s.name, c): threading.Lock() for s in sessions.values() for c in s.cameras
        }
        self._queue: queue.Queue[int | None] = queue.Queue()
        self._worker = threading.Thread(target=self._prefetch_loop, daemon=True)
        self._worker.start()

    def _get(self, key: tuple[str, int, str]) -> bytes | None:
        with self._cache_lock:
            data = self._cache.get(key)
            if data is not None:
                self._cache.move_to_end(key)
            return data

    def _put(self, key: tuple[str, int, str], data: bytes) -> None:
        with self._cache_lock:
            self._cache[key] = data
            self._cache.move_to_end(key)
            while len(self._cache) > self._max:
                self._cache.popitem(last=False)

    def jpeg(self, index: int, camera: str) -> bytes:
        """The JPEG image of ``camera`` at instant ``index`` (decoded now unless cached).

        Raises:
            KeyError: the camera is not in the instant's session.
            MediaError: the frame cannot be decoded.
        """
        x = self.instants[index]
        if camera not in self.sessions[x.session].cameras:
            raise KeyError(camera)
        key = (x.session, x.frame, camera)
        data = self._get(key)
        if data is not None:
            return data
        src_key = (x.session, camera)
        with self._source_locks[src_key]:  # one decoder per video; waits for a prefetch
            data = self._get(key)
            if data is not None:
                return data
            src = self._sources.get(src_key)
            if src is None:
                src = FrameSource(self.sessions[x.session].videos[camera])
                self._sources[src_key] = src
            frame = src.read(x.frame)
        ok, buf = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, self.quality])
        if not ok:
            raise RuntimeError(f"JPEG encoding failed for {x.session} {camera} {x.frame}")
        data = buf.tobytes()
        self._put(key, data)
        return data

    def prefetch(self, indices: Sequence[int]) -> None:
        """Decode these instants in the background (skipped when cached)."""
        for i in indices:
            if 0 <= i < len(self.instants):
                self._queue.put(int(i))

    def _prefetch_loop(self) -> None:
        while True:
            i = self._queue.get()
            if i is None:
                return
            cams = self.sessions[self.instants[i].session].cameras
            for cam in cams:
                try:
                    self.jpeg(i, cam)
                except Exception as exc:  # a prefetch failure shows when the page asks
                    log.debug("prefetch of instant %d camera %s failed: %s", i, cam, exc)

    def close(self) -> None:
        """Stop the prefetch thread and release the videos."""
        self._queue.put(None)
        self._worker.join(timeout=5)
        for key, src in self._sources.items():
            with self._source_locks[key]:
                src.close()
