"""Board detection in every frame of every camera, in parallel processes, with a cache.

The frames are split into chunks (:func:`plan_chunks`) that this process and worker
processes take one at a time; each chunk is decoded once, in order, and tracked with
:class:`~freipose.calibration.tracking.BoardTracker`. Results are cached by
:mod:`freipose.calibration.detection_cache`.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

from freipose.calibration.boards import Board
from freipose.calibration.detect import CameraDetections, board_side
from freipose.calibration.detection_cache import cache_file, load_cache, save_cache
from freipose.calibration.tracking import BoardTracker
from freipose.workers import pool_context, process_pool, start_manager, worker_errors

if TYPE_CHECKING:  # the bar: a tqdm bar or a freipose.progress.LineProgress
    from tqdm import tqdm

logger = logging.getLogger(__name__)

__all__ = ["CHUNK_FRAMES", "PROGRESS_EVERY", "detect_cameras", "plan_chunks"]

PROGRESS_EVERY = 10  # frames between progress messages of a worker
# frames per detection chunk: a chunk is one sequential decode (one seek), handed to whichever
# process is free; small enough to keep every process busy to the end
CHUNK_FRAMES = 100


class ProgressSink(Protocol):
    """Where a detection chunk reports its progress (a queue, or :class:`_BarTicks`)."""

    def put(self, n: int) -> None:
        """Take a report of ``n`` more frames done."""


def _init_worker() -> None:
    """Detection worker: one OpenCV thread (the parallelism is across processes)."""
    import cv2

    cv2.setNumThreads(1)


def _detect_chunk(
    path: str, board: Board, start: int, stop: int, progress: ProgressSink | None = None
) -> tuple[int, np.ndarray]:
    """Detect the board in frames ``start..stop-1`` of one source, decoding each frame once.

    Frames are read sequentially (one seek at ``start`` at most).

    Args:
        path: the video file or image folder.
        board: the board.
        start: the first frame.
        stop: one past the last frame.
        progress: receives (``put``) the number of frames done every few frames; ``None``:
            no progress reports.

    Returns:
        ``start`` and the (stop - start, P, 2) detections.
    """
    from freipose.io.video import FrameSource

    det = BoardTracker(board)
    out = np.full((stop - start, det.P, 2), np.nan)
    done = 0
    # cache_size=1 keeps frame 0, which opening the source decodes, so a chunk starting at 0
    # does not seek back to it
    folder = Path(path).is_dir()
    with FrameSource(path, cache_size=1) as src:
        for i in range(start, stop):
            # consecutive video frames: search around the previous frame's board first
            # (image folders hold unrelated photos: the whole image each time)
            out[i - start] = det(src.read(i)) if folder else det.track(src.read(i))
            done += 1
            if progress is not None and done == PROGRESS_EVERY:
                progress.put(done)
                done = 0
    if progress is not None and done:
        progress.put(done)
    return start, out


def plan_chunks(
    frames: Sequence[int], chunk_frames: int = CHUNK_FRAMES
) -> list[tuple[int, int, int]]:
    """Split cameras into contiguous ``(camera, start, stop)`` chunks of frames.

    Each chunk is decoded sequentially (a seek costs OpenCV many decoded frames) and tracks
    the board from its first frame on; the chunks do not depend on the number of processes,
    so neither do the detections.

    Args:
        frames: the frame count of every camera.
        chunk_frames: the most frames per chunk; a camera's chunks are of equal length (to
            one frame).

    Returns:
        the chunks, longest first.
    """
    out: list[tuple[int, int, int]] = []
    for ci, n in enumerate(frames):
        if n <= 0:
            continue
        pieces = -(-int(n) // max(1, int(chunk_frames)))
        edges = np.linspace(0, n, pieces + 1).round().astype(int)
        out.extend((ci, int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a)
    # longest first, so that the last chunks to finish are short
    return sorted(out, key=lambda c: c[1] - c[2])


def detect_cameras(
    sources: Sequence[str | Path],
    board: Board,
    cache_dir: str | Path | None = None,
    jobs: int | None = None,
    progress: bool = True,
) -> list[CameraDetections]:
    """Detect the board in every frame of every camera (video files or image folders).

    Frames are split into contiguous chunks (see :func:`plan_chunks`; every frame is decoded
    once) that run in ``jobs`` processes, this one and ``jobs - 1`` workers, with one
    OpenCV thread each (default: the CPU count; ``1``: this process only). Results are cached
    in ``cache_dir`` keyed by video and board hash, so a second call with the same inputs does
    not re-detect.

    Args:
        sources: one video file or image folder per camera.
        board: the board.
        cache_dir: folder of the detection cache; ``None``: no cache.
        jobs: processes (default: the CPU count).
        progress: show a progress bar.

    Returns:
        one :class:`CameraDetections` per source, in order, with the side of the board seen
        in every frame (:func:`~freipose.calibration.detect.board_side`).

    Raises:
        WorkerError: a worker process died (the message says how, in one line).
    """
    from freipose.io.video import FrameSource
    from freipose.progress import progress_bar

    sources = [Path(s) for s in sources]
    infos = []
    for s in sources:
        with FrameSource(s) as src:
            infos.append((src.name, src.size, src.num_frames))
    P = len(board.object_points)
    results: dict[int, np.ndarray] = {}
    todo_frames = [0] * len(sources)
    cache_paths: dict[int, Path] = {}
    for ci, (s, (_name, _size, n)) in enumerate(zip(sources, infos)):
        if cache_dir is not None:
            cp = cache_file(Path(cache_dir), s, board)
            cache_paths[ci] = cp
            if cp.is_file():
                pts = load_cache(cp, n, P)
                if pts is not None:
                    logger.info("%s: using cached detections %s", s, cp)
                    results[ci] = pts
                    continue
        results[ci] = np.full((n, P, 2), np.nan)
        todo_frames[ci] = n
    if jobs is None:
        jobs = os.cpu_count() or 1
    todo = plan_chunks(todo_frames)
    total = sum(b - a for _, a, b in todo)
    jobs = max(1, min(int(jobs), len(todo) or 1))
    bar = progress_bar(
        total=total,
        desc="detecting board",
        unit="frame",
        disable=None if progress and total else True,
    )
    try:
        if jobs == 1:
            ticks = None if bar.disable else _BarTicks(bar)
            for ci, a, b in todo:
                _, pts = _detect_chunk(str(sources[ci]), board, a, b, ticks)
                results[ci][a:b] = pts
        elif todo:
            _detect_parallel(sources, board, todo, jobs, results, bar)
    finally:
        bar.close()
    done = {ci for ci, _, _ in todo}
    for ci in done:
        if ci in cache_paths:
            save_cache(cache_paths[ci], results[ci])
    obj = board.object_points
    return [
        CameraDetections(name, size, results[ci], str(sources[ci]), board_side(results[ci], obj))
        for ci, (name, size, _n) in enumerate(infos)
    ]


class _BarTicks:
    """Progress sink for detection in this process.

    ``put(n)`` advances the bar, then calls ``then()`` (when given; in parallel: take in the
    workers' reports).

    Args:
        bar: the tqdm progress bar.
        then: called after every advance; ``None``: nothing.
    """

    def __init__(self, bar: tqdm, then: Callable[[], None] | None = None):
        self.bar = bar
        self.then = then

    def put(self, n: int) -> None:
        """Advance the bar by ``n`` frames."""
        self.bar.update(n)
        if self.then is not None:
            self.then()


def _join(threads: Sequence[threading.Thread], between: Callable[[], None]) -> None:
    """Wait for ``threads`` to end, calling ``between()`` every 0.25 s and once at the end."""
    while any(t.is_alive() for t in threads):
        for t in threads:
            t.join(timeout=0.25)
        between()
    between()


def _detect_parallel(
    sources: Sequence[str | Path],
    board: Board,
    todo: Sequence[tuple[int, int, int]],
    jobs: int,
    results: dict[int, np.ndarray],
    bar: tqdm,
) -> None:
    """Run ``todo`` chunks in this process and ``jobs - 1`` worker processes.

    The chunks are handed out one at a time, to whichever process is free: this process
    starts at once, while the workers start (a fresh interpreter importing OpenCV).

    Args:
        sources: the cameras' video files or image folders.
        board: the board.
        todo: the ``(camera, start, stop)`` chunks.
        jobs: processes, this one included.
        results: per camera, the (F, P, 2) detections, filled in place.
        bar: the tqdm progress bar, advanced as frames are done.

    Raises:
        WorkerError: a worker process died (the message says how, in one line).
    """
    import queue as queue_mod
    from collections import deque

    from freipose.io.video import opencv_threads

    # the forkserver imports this module once; workers fork from it ready to run
    # (cv2 starts no threads on import)
    preload = [__name__, "cv2"]
    ctx = pool_context(preload)
    # the progress queue's server process forks from the same clean server
    manager = start_manager(ctx) if not bar.disable else None
    ticks = manager.Queue() if manager is not None else None
    pending = deque(todo)
    lock = threading.Lock()
    errors: list[BaseException] = []

    def take() -> tuple[int, int, int] | None:
        with lock:
            return pending.popleft() if pending else None

    def stop() -> None:
        with lock:
            pending.clear()

    def drain() -> None:
        while ticks is not None:
            try:
                bar.update(ticks.get_nowait())
            except queue_mod.Empty:
                return

    def work(run: Callable[[int, int, int], np.ndarray]) -> None:
        """Take chunks until none is left; ``run(ci, a, b)`` detects one: its points."""
        while (chunk := take()) is not None:
            ci, a, b = chunk
            results[ci][a:b] = run(ci, a, b)

    def feed(ex: ProcessPoolExecutor) -> None:
        """Keep one worker busy: submit the next chunk when it has finished the last."""

        def run(ci: int, a: int, b: int) -> np.ndarray:
            return ex.submit(_detect_chunk, str(sources[ci]), board, a, b, ticks).result()[1]

        try:
            work(run)
        except BaseException as e:  # re-raised in the main thread
            errors.append(e)
            stop()

    try:
        with (
            process_pool(jobs - 1, preload=preload, initializer=_init_worker) as ex,
            worker_errors(ex),
        ):
            feeders = [
                threading.Thread(target=feed, args=(ex,), daemon=True) for _ in range(jobs - 1)
            ]
            for t in feeders:
                t.start()
            # this process's progress: its own frames, then the workers' reported so far
            mine = None if bar.disable else _BarTicks(bar, drain)
            try:
                with opencv_threads(1):  # like the workers: the parallelism is across processes
                    work(lambda ci, a, b: _detect_chunk(str(sources[ci]), board, a, b, mine)[1])
            except BaseException:
                stop()
                raise
            finally:
                _join(feeders, drain)
            if errors:
                raise errors[0]
    finally:
        if manager is not None:
            manager.shutdown()
