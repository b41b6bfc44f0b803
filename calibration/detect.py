"""Board detection in images and videos, in parallel processes, with an on-disk cache.

Detections of one camera are a dense ``(F, P, 2)`` float64 array of pixel coordinates (pixel-centre
convention), NaN where board point ``p`` was not found in frame ``f``.
"""

from __future__ import annotations

import hashlib
import logging
import os
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from freipose.calibration.boards import (
    AprilGridBoard,
    Board,
    CharucoBoard,
    ChessboardBoard,
    board_dictionary,
    board_hash,
    get_dictionary,
)

logger = logging.getLogger(__name__)

__all__ = [
    "CameraDetections",
    "DetectionError",
    "detect_image",
    "detect_cameras",
    "diagnose_board",
    "CACHE_VERSION",
]

CACHE_VERSION = 3  # 2: ChArUco markers from two threshold windows; 3: fast search in videos
PROGRESS_EVERY = 10  # frames between progress messages of a worker
# frames per detection chunk: a chunk is one sequential decode (one seek), handed to whichever
# process is free; ~100 frames keep two to a few dozen processes busy to the end
CHUNK_FRAMES = 100
CHARUCO_THRESH_WINDOWS = (3, 13)  # px, smallest and largest adaptive-threshold window (ChArUco)
CHARUCO_FAST_WINDOW = 3  # px, the one threshold window of the fast search in videos
EXPECTED_MARGIN = 4.0  # px: a marker counts as expected when predicted this far inside
TRACK_GROW = 0.3  # search window around the previous frame's board: grown by this fraction


class DetectionError(ValueError):
    """The board cannot be detected (and the message says what was seen instead)."""


@dataclass(frozen=True)
class CameraDetections:
    """Board corners found in every frame of one camera.

    Attributes:
        name: camera name (video stem).
        size: image (width, height).
        points: (F, P, 2) pixel coordinates, NaN where not detected.
        source: the video file or image folder.
    """

    name: str
    size: tuple[int, int]
    points: np.ndarray
    source: str = ""

    @property
    def num_frames(self) -> int:
        return int(self.points.shape[0])

    @property
    def mask(self) -> np.ndarray:
        """(F, P) bool: point detected."""
        return np.isfinite(self.points[..., 0])

    @property
    def counts(self) -> np.ndarray:
        """(F,) number of points detected per frame."""
        return self.mask.sum(axis=1)

    def truncated(self, n: int) -> CameraDetections:
        return CameraDetections(self.name, self.size, self.points[:n], self.source)


# --------------------------------------------------------------------------------------------
# single-image detection


def _gray(image: np.ndarray) -> np.ndarray:
    import cv2

    img = np.asarray(image)
    if img.ndim == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return img


def _subpix(gray: np.ndarray, pts: np.ndarray, win: int) -> np.ndarray:
    import cv2

    if len(pts) == 0:
        return pts
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 0.001)
    p = np.ascontiguousarray(pts.reshape(-1, 1, 2).astype(np.float32))
    out = cv2.cornerSubPix(gray, p, (win, win), (-1, -1), crit)
    return np.asarray(out, dtype=np.float64).reshape(-1, 2)


def _detect_charuco(gray: np.ndarray, board: CharucoBoard, detector=None):
    ids, pts, _markers = _detect_charuco_markers(gray, board, detector)
    return ids, pts


def _detect_charuco_markers(gray: np.ndarray, board: CharucoBoard, detector=None):
    """``(corner ids (N,), corners (N, 2), marker ids (M,))`` of one ChArUco detection."""
    if detector is None:
        detector = _charuco_detector(board)
    cc, ci, _mc, mi = detector.detectBoard(gray)
    markers = np.zeros(0, np.int64) if mi is None else np.asarray(mi, np.int64).reshape(-1)
    if ci is None or cc is None or len(ci) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 2)), markers
    return (
        np.asarray(ci, np.int64).reshape(-1),
        np.asarray(cc, np.float64).reshape(-1, 2),
        markers,
    )


def _charuco_detector(board: CharucoBoard, windows: tuple[int, int] | None = None):
    """OpenCV ChArUco detector whose markers come from adaptive-threshold windows
    ``windows`` = (smallest, largest) px, step 10 (default :data:`CHARUCO_THRESH_WINDOWS`).

    Its dictionary holds only the board's markers (:func:`board_dictionary`): the same
    detections as with the whole dictionary, in about half the time, since each marker
    candidate that is not a marker (the board's black squares, ~half the candidates) was
    compared with every dictionary entry (on the six 640 x 480 benchmark rigs: identical
    points in all 3600 frames; 2.3-3.4 -> 1.4-2.0 ms per frame)."""
    import cv2

    cp = cv2.aruco.CharucoParameters()
    cp.minMarkers = 2  # a corner needs both neighbouring markers (no edge artefacts)
    dp = cv2.aruco.DetectorParameters()
    # marker candidates from two adaptive-threshold windows (3 and 13 px) instead of OpenCV's
    # three (3, 13, 23): detection ~30 % faster; on the rendered benchmark rigs (640 x 480,
    # markers 15-60 px) 0.1-0.5 % fewer corners, with the same corner accuracy (median error
    # against the truth 0.059 / 0.053 px either way). Bits are read from the image, not from
    # the thresholded one, so large markers are still found: their outline is an edge at any
    # window size.
    dp.adaptiveThreshWinSizeMin, dp.adaptiveThreshWinSizeMax = windows or CHARUCO_THRESH_WINDOWS
    return cv2.aruco.CharucoDetector(board.cv_board(board_markers_only=True), cp, dp)


def _detect_chessboard(gray: np.ndarray, board: ChessboardBoard):
    import cv2

    nx, ny = board.inner_corners_x, board.inner_corners_y
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
    ok, corners = cv2.findChessboardCorners(gray, (nx, ny), flags=flags)
    if not ok or corners is None:
        return np.zeros(0, np.int64), np.zeros((0, 2))
    pts = np.asarray(corners, np.float64).reshape(-1, 2)  # OpenCV 5 gives (N,2), 4.x (N,1,2)
    # window: a third of the smallest corner spacing, at least 2 px
    grid = pts.reshape(ny, nx, 2)
    spacing = min(
        np.linalg.norm(np.diff(grid, axis=1), axis=-1).min(),
        np.linalg.norm(np.diff(grid, axis=0), axis=-1).min(),
    )
    win = int(np.clip(spacing / 3, 2, 11))
    pts = _subpix(gray, pts, win)
    grid = pts.reshape(ny, nx, 2)
    # orientation: OpenCV may return the grid rotated by 180 degrees. Square (0, 0) (outside
    # corner 0) is black on our board, its neighbour (1, 0) white; compare their intensities.
    g00, g10, g01 = grid[0, 0], grid[0, 1], grid[1, 0]
    c_sq00 = g00 - 0.5 * (g10 - g00) - 0.5 * (g01 - g00)
    c_sq10 = g00 + 0.5 * (g10 - g00) - 0.5 * (g01 - g00)
    if (nx + ny) % 2 == 1 and _intensity(gray, c_sq00) > _intensity(gray, c_sq10):
        pts = pts[::-1].copy()
    return np.arange(nx * ny, dtype=np.int64), pts


def _intensity(gray: np.ndarray, xy: np.ndarray) -> float:
    h, w = gray.shape[:2]
    x = int(round(float(np.clip(xy[0], 0, w - 1))))
    y = int(round(float(np.clip(xy[1], 0, h - 1))))
    patch = gray[max(0, y - 1) : y + 2, max(0, x - 1) : x + 2]
    return float(patch.mean())


def _aruco_detector(dictionary_name: str, border_bits: int = 1, num_markers: int | None = None):
    """OpenCV marker detector for a named dictionary; with ``num_markers`` it only knows ids
    0..num_markers-1 (:func:`~freipose.calibration.boards.board_dictionary`: the same detections of
    those markers, faster)."""
    import cv2

    p = cv2.aruco.DetectorParameters()
    p.markerBorderBits = int(border_bits)
    p.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
    if num_markers is None:
        dictionary = get_dictionary(dictionary_name)
    else:
        dictionary = board_dictionary(dictionary_name, num_markers)
    return cv2.aruco.ArucoDetector(dictionary, p)


def _detect_aprilgrid(gray: np.ndarray, board: AprilGridBoard, detector=None):
    if detector is None:
        detector = _aruco_detector(board.dictionary, board.border, board.n_tags)
    corners, ids, _ = detector.detectMarkers(gray)
    if ids is None or len(ids) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 2))
    ids = np.asarray(ids, np.int64).reshape(-1)
    corners = [np.asarray(c, np.float64).reshape(4, 2) for c in corners]
    keep = ids < board.n_tags
    if not keep.any():
        return np.zeros(0, np.int64), np.zeros((0, 2))
    ids = ids[keep]
    cs = np.stack([c for c, k in zip(corners, keep) if k])  # (M, 4, 2) TL TR BR BL
    side = np.linalg.norm(cs - np.roll(cs, 1, axis=1), axis=-1).min()
    # the tag corners are X-junctions with the black corner squares: refine on them
    win = int(np.clip(side * board.tag_spacing / 2.5, 2, 9))
    pts = _subpix(gray, cs.reshape(-1, 2), win).reshape(-1, 4, 2)
    order = np.asarray(board.OPENCV_TO_CORNER)
    pid = (4 * ids[:, None] + order[None, :]).reshape(-1)
    return pid, pts.reshape(-1, 2)


def detect_image(image: np.ndarray, board: Board) -> tuple[np.ndarray, np.ndarray]:
    """Detect the board in one image.

    Args:
        image: (H, W, 3) BGR or (H, W) gray uint8.
        board: the board.

    Returns:
        ``(ids (N,) int, corners (N, 2) float64)``: point ids into ``board.object_points`` and
        their pixel coordinates; empty when the board is not found.
    """
    gray = _gray(image)
    if isinstance(board, CharucoBoard):
        return _detect_charuco(gray, board)
    if isinstance(board, ChessboardBoard):
        return _detect_chessboard(gray, board)
    if isinstance(board, AprilGridBoard):
        return _detect_aprilgrid(gray, board)
    raise TypeError(f"unsupported board {type(board).__name__}")


def _box_spacing(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Bounding box ``(lo (2,), hi (2,))`` of points (M, 2) px and their typical spacing (px):
    the side of the box's area shared out among the points."""
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    ext = hi - lo
    return lo, hi, float(np.sqrt(max(ext[0] * ext[1], 1.0) / len(pts)))


def _track_window(prev: np.ndarray, shape: tuple[int, ...]) -> tuple[int, int, int, int]:
    """Search window ``(x0, y0, x1, y1)`` around the previous frame's points (M, 2): their box
    grown by 30 % of its size plus two point spacings and 16 px on each side (the board's
    motion between frames), clipped to the image."""
    lo, hi, spacing = _box_spacing(prev)
    m = TRACK_GROW * float((hi - lo).max()) + 2 * spacing + 16
    h, w = shape[:2]
    x0, y0 = int(max(0, lo[0] - m)), int(max(0, lo[1] - m))
    x1, y1 = int(min(w, np.ceil(hi[0] + m) + 1)), int(min(h, np.ceil(hi[1] + m) + 1))
    return x0, y0, x1, y1


def _clear_of_window_edges(
    pts: np.ndarray, win: tuple[int, int, int, int], shape: tuple[int, ...]
) -> bool:
    """Whether the points found in the window (image px) stay clear of the window's edges that
    are not image edges: a board point further out would have been cut off (with its marker),
    so the window's result is complete only then."""
    lo, hi, spacing = _box_spacing(pts)
    guard = 1.5 * spacing + 5
    x0, y0, x1, y1 = win
    h, w = shape[:2]
    return bool(
        (x0 == 0 or lo[0] - x0 > guard)
        and (y0 == 0 or lo[1] - y0 > guard)
        and (x1 == w or x1 - hi[0] > guard)
        and (y1 == h or y1 - hi[1] > guard)
    )


class _Detector:
    """Reusable per-process detector (builds OpenCV objects once).

    ``detector(image)`` searches the whole image. ``detector.track(image)``, for consecutive
    frames of one video, first searches a window around the previous frame's detection and
    keeps that result when at least 4 points were found clear of the window's edges;
    otherwise (and when the previous frame had no board) it searches the whole image. The
    image-wide part of the marker search costs by area, so this saves ~30 % per frame with a
    board on videos where it covers a small part of the view. With the same (two-window)
    search in the window, the points are those of the whole-image search: on the six rendered
    benchmark rigs (3600 frames, 30,468 corners; 2540 frames served by the window) 5 corners
    were found by only one of the two searches and 11 moved (at most 0.9 px: cornerSubPix
    converging elsewhere).

    For ChArUco boards ``track`` also searches first with one adaptive-threshold window
    (:data:`CHARUCO_FAST_WINDOW`) instead of two, and keeps that result only when it has every
    marker that the previous frame's board, carried over by the homography of its corners,
    puts inside the window (and its corners are clear of the window's edges); otherwise the
    two-window search runs. Whole-image searches in videos start with the one window too and
    stop there when it finds no marker at all (no board in view). On rendered rigs 1-3 of the
    calibration benchmark (1800 frames, 15,290 corners; 1108 frames served by the one-window
    search) 9 corners differ in presence from the whole-image two-window search and 410 moved
    by more than 0.01 px (99.9 % by less than 0.13 px: OpenCV stops cornerSubPix at 0.1 px
    steps, so its start, the marker outlines, shows through); the median error against the
    true corners is 0.0560 px either way. Detection costs ~20 % less per frame (2.33 vs 2.95
    ms on rigs 2 and 5, one thread).
    """

    def __init__(self, board: Board):
        self.board = board
        self.P = len(board.object_points)
        self._cv = None
        self._fast = None
        self._prev: np.ndarray | None = None
        self._prev_ids: np.ndarray | None = None
        self.windowed = 0  # frames that the window search served (statistics)
        self.fast = 0  # frames that the one-window search served (statistics)
        if isinstance(board, CharucoBoard):
            self._cv = _charuco_detector(board)
            self._fast = _charuco_detector(board, (CHARUCO_FAST_WINDOW, CHARUCO_FAST_WINDOW))
            cvb = self._cv.getBoard()
            # board-plane coordinates of the ChArUco corners (P, 2) and marker outlines (M, 4, 2)
            self._corners_2d = np.asarray(cvb.getChessboardCorners(), np.float64)[:, :2]
            self._markers_2d = np.asarray(cvb.getObjPoints(), np.float64)[:, :, :2]
            self._marker_ids = np.asarray(cvb.getIds(), np.int64).reshape(-1)
        elif isinstance(board, AprilGridBoard):
            self._cv = _aruco_detector(board.dictionary, board.border, board.n_tags)

    def _detect(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        b = self.board
        if isinstance(b, CharucoBoard):
            return _detect_charuco(gray, b, self._cv)
        if isinstance(b, AprilGridBoard):
            return _detect_aprilgrid(gray, b, self._cv)
        return _detect_chessboard(gray, b)

    def _points(self, ids: np.ndarray, pts: np.ndarray) -> np.ndarray:
        out = np.full((self.P, 2), np.nan)
        ok = (ids >= 0) & (ids < self.P)
        out[ids[ok]] = pts[ok]
        return out

    def __call__(self, image: np.ndarray) -> np.ndarray:
        return self._points(*self._detect(_gray(image)))

    def _expected_markers(self, win: tuple[int, int, int, int]) -> np.ndarray | None:
        """Marker ids (E,) that the previous frame's board, mapped by the homography of its
        corners, puts inside ``win`` with :data:`EXPECTED_MARGIN`; None when there is no
        usable homography or no such marker."""
        import cv2

        H, _ = cv2.findHomography(self._corners_2d[self._prev_ids], self._prev, 0)
        if H is None or not np.all(np.isfinite(H)):
            return None
        q = cv2.perspectiveTransform(self._markers_2d.reshape(-1, 1, 2), H).reshape(-1, 4, 2)
        x0, y0, x1, y1 = win
        m = EXPECTED_MARGIN
        inside = (
            (q[..., 0] >= x0 + m)
            & (q[..., 0] <= x1 - 1 - m)
            & (q[..., 1] >= y0 + m)
            & (q[..., 1] <= y1 - 1 - m)
        ).all(axis=1)
        return self._marker_ids[inside] if inside.any() else None

    def _fast_window(self, crop: np.ndarray, win) -> tuple[np.ndarray, np.ndarray] | None:
        """The one-window search in the tracking window, when it has every expected marker."""
        expected = self._expected_markers(win)
        if expected is None:
            return None
        ids, pts, markers = _detect_charuco_markers(crop, self.board, self._fast)
        if len(ids) < 4 or not np.isin(expected, markers).all():
            return None
        return ids, pts

    def track(self, image: np.ndarray) -> np.ndarray:
        """Detect in the next frame of a video (see the class docstring); (P, 2) px, NaN where
        a point is not found."""
        gray = _gray(image)
        out = None
        if self._prev is not None:
            win = _track_window(self._prev, gray.shape)
            x0, y0, x1, y1 = win
            crop = np.ascontiguousarray(gray[y0:y1, x0:x1])
            for fast in (True, False) if self._fast is not None else (False,):
                found = self._fast_window(crop, win) if fast else self._detect(crop)
                if found is None or len(found[0]) < 4:
                    continue
                ids, pts = found[0], found[1] + np.array([x0, y0], np.float64)
                if _clear_of_window_edges(pts, win, gray.shape):
                    out = self._points(ids, pts)
                    self.windowed += 1
                    self.fast += fast
                    break
        if out is None and self._fast is not None:
            _ids, _pts, markers = _detect_charuco_markers(gray, self.board, self._fast)
            if len(markers) == 0:  # nothing marker-like in view: no board
                out = np.full((self.P, 2), np.nan)
        if out is None:
            out = self._points(*self._detect(gray))
        found = np.isfinite(out[:, 0])
        if found.sum() >= 4:
            self._prev, self._prev_ids = out[found], np.flatnonzero(found)
        else:
            self._prev = self._prev_ids = None
        return out


# --------------------------------------------------------------------------------------------
# videos, in parallel, cached


def _init_worker() -> None:
    """Detection worker: one OpenCV thread (the parallelism is across processes)."""
    import cv2

    cv2.setNumThreads(1)


def _detect_chunk(
    path: str, board: Board, start: int, stop: int, progress=None
) -> tuple[int, np.ndarray]:
    """Detect the board in frames ``start..stop-1`` of one source, decoding each frame once.

    Frames are read sequentially (one seek at ``start`` at most); ``progress`` (a queue, or
    None) receives the number of frames done every few frames.
    """
    from freipose.io.video import FrameSource

    det = _Detector(board)
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
    """Split cameras with ``frames[c]`` frames into contiguous ``(camera, start, stop)`` chunks
    of at most ``chunk_frames`` frames, of equal length within a camera (to one frame).

    Each chunk is decoded sequentially (a seek costs OpenCV about 16 decoded frames) and
    tracks the board from its first frame on; the chunks do not depend on the number of
    processes, so neither do the detections. Returned longest first.
    """
    out = []
    for ci, n in enumerate(frames):
        if n <= 0:
            continue
        pieces = -(-int(n) // max(1, int(chunk_frames)))
        edges = np.linspace(0, n, pieces + 1).round().astype(int)
        out.extend((ci, int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a)
    # longest first, so that the last chunks to finish are short
    return sorted(out, key=lambda c: c[1] - c[2])


def _source_signature(path: Path) -> str:
    """Hash of the absolute path, size and modification time (files) or listing (folders)."""
    p = path.resolve()
    h = hashlib.sha1(str(p).encode())
    if p.is_dir():
        for f in sorted(p.iterdir()):
            st = f.stat()
            h.update(f"{f.name}:{st.st_size}:{st.st_mtime_ns}".encode())
    else:
        st = p.stat()
        h.update(f"{st.st_size}:{st.st_mtime_ns}".encode())
    return h.hexdigest()[:12]


def cache_file(cache_dir: Path, source: Path, board: Board) -> Path:
    """Cache path for one camera's detections: ``<stem>-<video hash>-<board hash>.npz``."""
    name = source.stem if source.is_file() else source.name
    return Path(cache_dir) / f"{name}-{_source_signature(source)}-{board_hash(board)}.npz"


def _load_cache(path: Path, num_frames: int, num_points: int) -> np.ndarray | None:
    try:
        with np.load(path) as z:
            if int(z["version"]) != CACHE_VERSION:
                return None
            pts = np.asarray(z["points"], np.float64)
    except (OSError, KeyError, ValueError):
        return None
    if pts.shape != (num_frames, num_points, 2):
        return None
    return pts


def _save_cache(path: Path, points: np.ndarray) -> None:
    from freipose.io.atomic import atomic_path

    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, points=points, version=np.int64(CACHE_VERSION))


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

    Returns:
        one :class:`CameraDetections` per source, in order.
    """
    from tqdm import tqdm

    from freipose.io.video import FrameSource

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
                pts = _load_cache(cp, n, P)
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
    bar = tqdm(
        total=total, desc="detecting board", unit="frame", disable=None if progress else True
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
            _save_cache(cache_paths[ci], results[ci])
    return [
        CameraDetections(name, size, results[ci], str(sources[ci]))
        for ci, (name, size, _n) in enumerate(infos)
    ]


class _BarTicks:
    """Progress sink for detection in this process: ``put(n)`` advances the bar, then calls
    ``then()`` (when given; in parallel: take in the workers' reports)."""

    def __init__(self, bar, then=None):
        self.bar = bar
        self.then = then

    def put(self, n: int) -> None:
        self.bar.update(n)
        if self.then is not None:
            self.then()


def _detect_parallel(sources, board, todo, jobs, results, bar) -> None:
    """Run ``todo`` chunks in this process and ``jobs - 1`` worker processes, filling
    ``results`` and advancing ``bar``.

    The chunks are handed out one at a time, to whichever process is free: this process
    starts at once, while the workers start (~0.2 s: a fresh interpreter importing OpenCV)."""
    import multiprocessing as mp
    import queue as queue_mod
    import threading
    from collections import deque

    from freipose.io.video import opencv_threads

    # forkserver: workers start from a clean process (forking a process whose OpenCV or
    # FFmpeg thread pools are running can deadlock the child)
    # (the server imports this module once; workers fork from it ready to run)
    if "forkserver" in mp.get_all_start_methods():
        ctx = mp.get_context("forkserver")
        ctx.set_forkserver_preload([__name__, "cv2"])  # cv2 starts no threads on import
    else:
        ctx = mp.get_context("spawn")
    # the progress queue's server process forks from the same clean server
    manager = ctx.Manager() if not bar.disable else None
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

    def work(run) -> None:
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
        with ProcessPoolExecutor(jobs - 1, mp_context=ctx, initializer=_init_worker) as ex:
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
                while any(t.is_alive() for t in feeders):
                    for t in feeders:
                        t.join(timeout=0.25)
                    drain()
            drain()
        if errors:
            raise errors[0]
    finally:
        if manager is not None:
            manager.shutdown()


# --------------------------------------------------------------------------------------------
# diagnosis: what board does the user probably have?


def _probe_dictionaries() -> list[tuple[str, int]]:
    """One dictionary per marker family (the largest), plus 2-bit borders for AprilTags."""
    import cv2

    # reversed: the lower-case alias (DICT_APRILTAG_36h11, our canonical name) comes first
    names = sorted((n for n in dir(cv2.aruco) if n.startswith("DICT_")), reverse=True)
    out, seen_ids = [], set()
    for n in names:
        value = getattr(cv2.aruco, n)
        if value in seen_ids:  # upper/lower-case aliases (DICT_APRILTAG_36H11 = _36h11)
            continue
        seen_ids.add(value)
        parts = n.split("_")
        if len(parts) == 3 and parts[2].isdigit() and parts[2] != "1000":
            continue  # DICT_4X4_50/100/250 are prefixes of DICT_4X4_1000
        out.append((n, 1))
        if n.startswith("DICT_APRILTAG") and "36h10" not in n.lower():
            out.append((n, 2))  # FreiCalib / Kalibr print 2-bit borders
    return sorted(out)


def _dict_len(name: str) -> int:
    return int(get_dictionary(name).bytesList.shape[0])


def _smallest_family_member(name: str, max_id: int) -> str:
    import cv2

    parts = name.split("_")
    if len(parts) == 3 and parts[2] == "1000":
        for size in (50, 100, 250, 1000):
            cand = f"{parts[0]}_{parts[1]}_{size}"
            if hasattr(cv2.aruco, cand) and max_id < size:
                return cand
    return name


def diagnose_board(images: Sequence[np.ndarray], board: Board) -> str:
    """Explain why ``board`` is not found in ``images`` by trying other boards.

    Tries every OpenCV marker dictionary (1- and 2-bit borders), the legacy ChArUco layout and
    other ChArUco sizes. Returns a sentence for the user (empty when nothing was found at all).
    """
    grays = [_gray(im) for im in images]
    hints: list[str] = []
    # 1. markers of which dictionary?
    found: dict[tuple[str, int], tuple[int, int]] = {}  # (dict, border) -> (count, max id)
    for dname, border in _probe_dictionaries():
        det = _aruco_detector(dname, border)
        count, max_id = 0, -1
        for g in grays:
            _c, ids, _ = det.detectMarkers(g)
            if ids is not None and len(ids):
                count += len(ids)
                max_id = max(max_id, int(np.max(ids)))
        if count:
            # nested dictionaries (4X4_50 is a prefix of 4X4_1000): name the smallest that fits
            dname = _smallest_family_member(dname, max_id)
            found[(dname, border)] = (count, max_id)
    own_dict = getattr(board, "dictionary", None)
    own_border = board.border if isinstance(board, AprilGridBoard) else 1
    if not found:
        if isinstance(board, ChessboardBoard):
            return (
                "no chessboard with the configured number of inner corners "
                f"({board.inner_corners_x}x{board.inner_corners_y}) and no markers were found; "
                "count the inner corners (squares minus one in each direction)"
            )
        return "no markers of any OpenCV dictionary were found in the sampled frames"
    top = max(c for c, _ in found.values())
    ties = [k for k, (c, _) in found.items() if c == top]
    own_fam = own_dict.rsplit("_", 1)[0] if own_dict else None
    same = [k for k in ties if k[1] == own_border and k[0].rsplit("_", 1)[0] == own_fam]
    if same and own_dict is not None and found[same[0]][1] < _dict_len(own_dict):
        dname, border = own_dict, own_border  # the configured dictionary holds every seen id
    else:  # the smallest dictionary holding every id seen
        dname, border = min(ties, key=lambda k: _dict_len(k[0]))
    count, max_id = found.get((dname, border)) or found[same[0]]
    if isinstance(board, ChessboardBoard):
        return (
            f"the images show {dname} markers ({count} found), not a plain chessboard; "
            f'describe the board as type = "charuco" or "aprilgrid"'
        )
    if dname != own_dict or border != own_border:
        hint = f"the images show markers of {dname}"
        if border != 1:
            hint += f" with a {border}-bit border"
        hint += f" ({count} found, ids up to {max_id}), but the board file says {own_dict}"
        if isinstance(board, AprilGridBoard) and own_dict == dname:
            hint += f" with border = {own_border}; set border = {border}"
        elif isinstance(board, AprilGridBoard) and not dname.startswith("DICT_APRILTAG"):
            hint += f'; is it a ChArUco board (type = "charuco", dictionary = "{dname}")?'
        elif dname.startswith("DICT_APRILTAG") and isinstance(board, CharucoBoard):
            fam = dname.replace("DICT_APRILTAG_", "")
            hint += f'; is it an AprilTag grid (type = "aprilgrid", family = "{fam}")?'
        else:
            hint += f'; set dictionary = "{dname}"'
        return hint
    # right dictionary
    if isinstance(board, CharucoBoard):
        if max_id >= board.n_markers:
            hints.append(
                f"markers with ids up to {max_id} were found but a {board.squares_x}x"
                f"{board.squares_y} board has only ids 0..{board.n_markers - 1}: "
                "the board is larger"
            )
        alt = []
        for sx, sy, legacy in _charuco_candidates(board, max_id):
            cand = CharucoBoard(
                sx, sy, board.square_size, board.marker_size, board.dictionary, legacy
            )
            n = sum(len(_detect_charuco(g, cand)[0]) for g in grays)
            if n:
                alt.append((n, -cand.n_markers, cand))
        if alt:
            n, _, cand = max(alt, key=lambda t: t[:2])
            desc = f"squares_x = {cand.squares_x}, squares_y = {cand.squares_y}"
            if cand.legacy_pattern != board.legacy_pattern and cand.squares_y % 2 == 0:
                desc += f", legacy_pattern = {str(cand.legacy_pattern).lower()}"
            hints.append(f"a board with {desc} finds {n} corners: that is probably your board")
        if not hints:
            hints.append(
                f"{count} {dname} markers were found but no ChArUco corners; check squares_x, "
                f"squares_y and legacy_pattern"
            )
        return "; ".join(hints)
    return (
        f"{count} {dname} markers were found (ids up to {max_id}) but no board corners; "
        f"check tags_x/tags_y"
    )


def _charuco_candidates(board: CharucoBoard, max_id: int) -> list[tuple[int, int, bool]]:
    """Plausible ChArUco layouts for the marker ids seen: the transposed board, the other
    legacy setting, and sizes whose marker count just covers the largest id."""
    need = max_id + 1
    out = [(board.squares_y, board.squares_x, board.legacy_pattern)]
    if board.squares_y % 2 == 0:
        out.append((board.squares_x, board.squares_y, not board.legacy_pattern))
    for sx in range(3, 13):
        for sy in range(3, 13):
            n = (sx * sy) // 2
            if need <= n <= need + min(sx, sy) // 2:
                out.append((sx, sy, False))
                if sy % 2 == 0:
                    out.append((sx, sy, True))
    own = (board.squares_x, board.squares_y, board.legacy_pattern)
    seen, uniq = set(), []
    for c in out:
        if c != own and c not in seen:
            seen.add(c)
            uniq.append(c)
    return uniq
