"""Board tracking through consecutive video frames: search near the last frame's board first."""

from __future__ import annotations

import numpy as np

from freipose.calibration.boards import AprilGridBoard, Board, CharucoBoard, ChessboardBoard
from freipose.calibration.detect import (
    aruco_detector,
    board_gray,
    charuco_detector,
    detect_aprilgrid,
    detect_aprilgrid_candidates,
    detect_charuco,
    detect_charuco_markers,
    detect_chessboard,
    mirror_x,
    quads,
)

__all__ = [
    "CHARUCO_FAST_WINDOW",
    "EXPECTED_MARGIN",
    "MIRROR_MIN_CANDIDATES",
    "TRACK_GROW",
    "BoardTracker",
]

CHARUCO_FAST_WINDOW = 3  # px, the one threshold window of the fast search in videos
EXPECTED_MARGIN = 4.0  # px: a marker counts as expected when predicted this far inside
TRACK_GROW = 0.3  # search window around the previous frame's board: grown by this fraction
# a frame without a board is searched mirrored when at least this many marker-like outlines that
# decode to none of the board's markers were found, and 3 times as many as markers that did (a
# mirrored marker is rejected or decodes to a wrong id; a board's black squares are rejected too)
MIRROR_MIN_CANDIDATES = 4


def _mirror_box(
    n_markers: int, rejected: np.ndarray, shape: tuple[int, ...]
) -> tuple[int, int, int, int] | None:
    """Where a frame without a board may show its mirror image: ``(x0, y0, x1, y1)`` or None.

    It is the box of the rejected marker candidates (R, 4, 2), grown by a quarter of its size
    and 16 px on each side, when there are :data:`MIRROR_MIN_CANDIDATES` and at least three
    times as many as markers found.
    """
    if len(rejected) < max(MIRROR_MIN_CANDIDATES, 3 * n_markers):
        return None
    pts = rejected.reshape(-1, 2)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    m = 0.25 * float((hi - lo).max()) + 16
    h, w = shape[:2]
    x0, y0 = int(max(0, lo[0] - m)), int(max(0, lo[1] - m))
    x1, y1 = int(min(w, np.ceil(hi[0] + m) + 1)), int(min(h, np.ceil(hi[1] + m) + 1))
    return (x0, y0, x1, y1) if x1 > x0 and y1 > y0 else None


def _box_spacing(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Bounding box ``(lo (2,), hi (2,))`` of points (M, 2) px and their typical spacing (px).

    The spacing is the side of the box's area shared out among the points.
    """
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    ext = hi - lo
    return lo, hi, float(np.sqrt(max(ext[0] * ext[1], 1.0) / len(pts)))


def _track_window(prev: np.ndarray, shape: tuple[int, ...]) -> tuple[int, int, int, int]:
    """Search window ``(x0, y0, x1, y1)`` around the previous frame's points (M, 2).

    The window is their box grown by :data:`TRACK_GROW` of its size plus two point spacings
    and 16 px on each side (the board's motion between frames), clipped to the image.
    """
    lo, hi, spacing = _box_spacing(prev)
    m = TRACK_GROW * float((hi - lo).max()) + 2 * spacing + 16
    h, w = shape[:2]
    x0, y0 = int(max(0, lo[0] - m)), int(max(0, lo[1] - m))
    x1, y1 = int(min(w, np.ceil(hi[0] + m) + 1)), int(min(h, np.ceil(hi[1] + m) + 1))
    return x0, y0, x1, y1


def _clear_of_window_edges(
    pts: np.ndarray, win: tuple[int, int, int, int], shape: tuple[int, ...]
) -> bool:
    """Whether the points found in the window (image px) stay clear of its inner edges.

    An inner edge is one that is not an image edge: a board point further out would have
    been cut off (with its marker), so the window's result is complete only then.
    """
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


class BoardTracker:
    """Reusable per-process detector of one board (builds the OpenCV objects once).

    ``tracker(image)`` searches the whole image. ``tracker.track(image)``, for consecutive
    frames of one video, first searches a window around the previous frame's detection and
    keeps that result when at least 4 points were found clear of the window's edges;
    otherwise (and when the previous frame had no board) it searches the whole image. The
    image-wide part of the marker search costs by area, so this is faster on videos where the
    board covers a small part of the view; with the same (two-window) search in the window,
    the points are those of the whole-image search but for cornerSubPix converging elsewhere
    now and then.

    For ChArUco boards ``track`` also searches first with one adaptive-threshold window
    (:data:`CHARUCO_FAST_WINDOW`) instead of two, and keeps that result only when it has every
    marker that the previous frame's board, carried over by the homography of its corners,
    puts inside the window (and its corners are clear of the window's edges); otherwise the
    two-window search runs. Whole-image searches in videos start with the one window too and
    stop there when it finds no marker at all (no board in view). The one-window corners move
    by less than OpenCV's cornerSubPix step (0.1 px) against the two-window ones, with the
    same accuracy against the true corners.

    Images of an inverted board are searched as their negative (:func:`board_gray`). A
    ChArUco board or AprilTag grid not found in a frame that shows many more marker-like
    outlines that decode to none of its markers than ones that do (:func:`_mirror_box`) is
    searched in the mirror image (a transparent or double-sided board seen from behind),
    first where those outlines are; a board found there is returned in the original image's
    pixels, and the next frames are tracked in the mirror image first, until it is lost. A
    chessboard is found from behind without this.

    Args:
        board: the board to detect.
    """

    def __init__(self, board: Board):
        import cv2

        self.board = board
        self.P = len(board.object_points)
        self._cv = None
        self._fast = None
        self._prev: np.ndarray | None = None
        self._prev_ids: np.ndarray | None = None
        self._side = 0  # 1: the previous frame's board was found in the mirror image
        self.windowed = 0  # frames that the window search served (statistics)
        self.fast = 0  # frames that the one-window search served (statistics)
        self.mirrored = 0  # frames whose board was found in the mirror image (statistics)
        self._mirror = not isinstance(board, ChessboardBoard)
        if isinstance(board, CharucoBoard):
            self._cv = charuco_detector(board)
            self._fast = charuco_detector(board, (CHARUCO_FAST_WINDOW, CHARUCO_FAST_WINDOW))
            cvb = self._cv.getBoard()
            # board-plane coordinates of the ChArUco corners (P, 2) and marker outlines (M, 4, 2)
            self._corners_2d = np.asarray(cvb.getChessboardCorners(), np.float64)[:, :2]
            self._markers_2d = np.asarray(cvb.getObjPoints(), np.float64)[:, :, :2]
            self._marker_ids = np.asarray(cvb.getIds(), np.int64).reshape(-1)
            # the markers of the one-window search (and its rejected candidates)
            fb = self._fast.getBoard()
            self._fast_markers = cv2.aruco.ArucoDetector(
                fb.getDictionary(), self._fast.getDetectorParameters()
            )
        elif isinstance(board, AprilGridBoard):
            self._cv = aruco_detector(board.dictionary, board.border, board.n_tags)

    def _detect(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        b = self.board
        if isinstance(b, CharucoBoard):
            return detect_charuco(gray, b, self._cv)
        if isinstance(b, AprilGridBoard):
            return detect_aprilgrid(gray, b, self._cv)
        return detect_chessboard(gray, b)

    def _points(self, ids: np.ndarray, pts: np.ndarray) -> np.ndarray:
        out = np.full((self.P, 2), np.nan)
        ok = (ids >= 0) & (ids < self.P)
        out[ids[ok]] = pts[ok]
        return out

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """(P, 2) px of the board points found anywhere in the image, NaN where not found.

        A ChArUco board or AprilTag grid that is not found is searched in the mirror image.
        """
        import cv2

        gray = board_gray(image, self.board)
        out = self._points(*self._detect(gray))
        if self._mirror and np.isfinite(out[:, 0]).sum() < 4:
            back = self._points(*self._detect(cv2.flip(gray, 1)))
            if np.isfinite(back[:, 0]).sum() >= 4:
                self.mirrored += 1
                return mirror_x(back, gray.shape[1])
        return out

    def _whole(self, gray: np.ndarray) -> tuple[np.ndarray, tuple[int, int, int, int] | None]:
        """Search the whole (board-dark) image: ``(points (P, 2), mirror box or None)``.

        A ChArUco search starts with the one-window marker search and stops there when it
        finds no marker. The box (:func:`_mirror_box`) is where the mirror image may show the
        board, from the marker candidates that decoded to none of the board's markers.
        """
        b = self.board
        if isinstance(b, CharucoBoard):
            _c, ids, rejected = self._fast_markers.detectMarkers(gray)
            n_ids = 0 if ids is None else len(ids)
            box = _mirror_box(n_ids, quads(rejected), gray.shape)
            if n_ids == 0:  # nothing marker-like in view: no board
                return np.full((self.P, 2), np.nan), box
            return self._points(*self._detect(gray)), box
        if isinstance(b, AprilGridBoard):
            pid, pts, n_ids, rejected = detect_aprilgrid_candidates(gray, b, self._cv)
            return self._points(pid, pts), _mirror_box(n_ids, rejected, gray.shape)
        return self._points(*self._detect(gray)), None

    def _mirrored(self, gray: np.ndarray, box: tuple[int, int, int, int]) -> np.ndarray:
        """The board in the mirror image of ``gray`` (px of the mirror image; NaN: not found).

        The whole mirror image is searched only when the mirrored ``box`` holds markers of
        the board: at least 3 ChArUco markers (4 corners need them), or one tag.
        """
        import cv2

        flipped = cv2.flip(gray, 1)
        w = gray.shape[1]
        x0, y0, x1, y1 = w - box[2], box[1], w - box[0], box[3]
        crop = np.ascontiguousarray(flipped[y0:y1, x0:x1])
        charuco = isinstance(self.board, CharucoBoard)
        detector = self._fast_markers if charuco else self._cv
        if detector is None:  # a chessboard: not searched mirrored
            return np.full((self.P, 2), np.nan)
        _c, ids, _r = detector.detectMarkers(crop)
        n_ids = 0 if ids is None else len(ids)
        if n_ids < (3 if charuco else 1):
            return np.full((self.P, 2), np.nan)
        return self._whole(flipped)[0]

    def _expected_markers(self, win: tuple[int, int, int, int]) -> np.ndarray | None:
        """Marker ids (E,) that the previous frame's board puts inside ``win``.

        The board is carried over by the homography of the previous frame's corners; a marker
        counts when all its corners are :data:`EXPECTED_MARGIN` inside. ``None`` when there is
        no usable homography or no such marker.
        """
        import cv2

        if self._prev is None or self._prev_ids is None:
            return None
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

    def _fast_window(
        self, crop: np.ndarray, win: tuple[int, int, int, int]
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """The one-window search in the tracking window, when it has every expected marker."""
        expected = self._expected_markers(win)
        if expected is None:
            return None
        ids, pts, markers = detect_charuco_markers(crop, self.board, self._fast)
        if len(ids) < 4 or not np.isin(expected, markers).all():
            return None
        return ids, pts

    def _track_in(self, gray: np.ndarray) -> tuple[np.ndarray, tuple[int, int, int, int] | None]:
        """Window search around the previous board, else whole image (see :meth:`_whole`)."""
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
                    self.windowed += 1
                    self.fast += fast
                    return self._points(ids, pts), None
        return self._whole(gray)

    def track(self, image: np.ndarray) -> np.ndarray:
        """Detect in the next frame of a video (see the class docstring).

        Args:
            image: (H, W, 3) BGR or (H, W) gray uint8 frame.

        Returns:
            (P, 2) px, NaN where a point is not found.
        """
        import cv2

        gray = board_gray(image, self.board)
        side = self._side  # search the side the previous frame showed first
        work = gray if side == 0 else cv2.flip(gray, 1)
        out, box = self._track_in(work)
        if self._mirror and box is not None and np.isfinite(out[:, 0]).sum() < 4:
            self._prev = self._prev_ids = None
            other = self._mirrored(work, box)
            if np.isfinite(other[:, 0]).sum() >= 4:
                out, side = other, 1 - side
        found = np.isfinite(out[:, 0])
        if found.sum() >= 4:
            self._prev, self._prev_ids = out[found], np.flatnonzero(found)
            self._side = side
        else:
            self._prev = self._prev_ids = None
            self._side = 0
        if side == 1:
            self.mirrored += int(found.sum() >= 4)
            return mirror_x(out, gray.shape[1])
        return out
