"""Board detection in one image, and the detections of one camera.

Detections of one camera are a dense ``(F, P, 2)`` float64 array of pixel coordinates
(pixel-centre convention), NaN where board point ``p`` was not found in frame ``f``.
Videos are searched by :mod:`freipose.calibration.detect_videos` (with the tracker of
:mod:`freipose.calibration.tracking`); :mod:`freipose.calibration.diagnose` explains a board
that is not found.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from freipose.calibration.boards import (
    AprilGridBoard,
    Board,
    CharucoBoard,
    ChessboardBoard,
    board_dictionary,
    get_dictionary,
)
from freipose.errors import FreiPoseError

if TYPE_CHECKING:  # OpenCV is imported where it is used
    import cv2

__all__ = [
    "CHARUCO_THRESH_WINDOWS",
    "CameraDetections",
    "DetectionError",
    "aruco_detector",
    "board_gray",
    "board_side",
    "charuco_detector",
    "detect_aprilgrid",
    "detect_aprilgrid_candidates",
    "detect_charuco",
    "detect_charuco_markers",
    "detect_chessboard",
    "detect_image",
    "gray_image",
    "mirror_x",
    "quads",
]

CHARUCO_THRESH_WINDOWS = (3, 13)  # px, smallest and largest adaptive-threshold window (ChArUco)


class DetectionError(FreiPoseError):
    """The board cannot be detected (and the message says what was seen instead)."""


@dataclass(frozen=True)
class CameraDetections:
    """Board corners found in every frame of one camera.

    Attributes:
        name: camera name (video stem).
        size: image (width, height).
        points: (F, P, 2) pixel coordinates, NaN where not detected.
        source: the video file or image folder.
        side: (F,) int8 side of the board seen: 0 front (or no board), 1 back (found in the
            mirror image: a transparent or double-sided board seen from behind); ``None``:
            not recorded (all front).
    """

    name: str
    size: tuple[int, int]
    points: np.ndarray
    source: str = ""
    side: np.ndarray | None = None

    @property
    def sides(self) -> np.ndarray:
        """(F,) int8 side of the board per frame (0 front or no board, 1 back)."""
        if self.side is None:
            return np.zeros(self.num_frames, np.int8)
        return np.asarray(self.side, np.int8)

    @property
    def back_views(self) -> int:
        """Number of frames in which the board's back was seen."""
        return int(np.count_nonzero(self.sides == 1))

    @property
    def num_frames(self) -> int:
        """F, the number of frames."""
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
        """The detections of the first ``n`` frames."""
        side = None if self.side is None else self.side[:n]
        return CameraDetections(self.name, self.size, self.points[:n], self.source, side)


def gray_image(image: np.ndarray) -> np.ndarray:
    """(H, W) gray version of a (H, W, 3) BGR image; a (H, W) image as it is."""
    import cv2

    img = np.asarray(image)
    if img.ndim == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return img


def board_gray(image: np.ndarray, board: Board) -> np.ndarray:
    """(H, W) gray image in which ``board`` is printed dark on light.

    It is the image's negative for an inverted board (white pattern on black), so that the
    detectors of normal prints find it; corner positions are those of the original image.
    """
    import cv2

    gray = gray_image(image)
    return cv2.bitwise_not(gray) if board.inverted else gray


def quads(corners: Sequence[np.ndarray] | None) -> np.ndarray:
    """OpenCV's marker outlines (a list of (1, 4, 2) arrays, or None) as one (N, 4, 2) array."""
    if corners is None or len(corners) == 0:
        return np.zeros((0, 4, 2))
    return np.concatenate([np.asarray(c, np.float64).reshape(-1, 4, 2) for c in corners])


def mirror_x(pts: np.ndarray, width: int) -> np.ndarray:
    """Points (..., 2) px of a horizontally flipped image in the original: x -> width - 1 - x."""
    out = np.array(pts, np.float64, copy=True)
    out[..., 0] = (width - 1) - out[..., 0]
    return out


def board_side(points: np.ndarray, object_points: np.ndarray) -> np.ndarray:
    """(F,) int8 side of the board seen per frame: 1 back, 0 front or fewer than 3 points.

    A board seen from behind is imaged mirrored: the affine map from board (x, y) to image
    (x, y) fitted to a frame's points has a negative determinant (positive from the front,
    where board x and y run like image x and y).

    Args:
        points: (F, P, 2) px, NaN where not detected.
        object_points: (P, 3) board points (mm).

    Returns:
        the side of every frame.
    """
    pts = np.asarray(points, np.float64)
    obj = np.asarray(object_points, np.float64)[:, :2]
    out = np.zeros(pts.shape[0], np.int8)
    found = np.isfinite(pts[..., 0])
    for f in np.flatnonzero(found.sum(axis=1) >= 3):
        m = found[f]
        a = np.column_stack([obj[m], np.ones(int(m.sum()))])
        coef, _res, rank, _sv = np.linalg.lstsq(a, pts[f, m], rcond=None)
        if rank == 3 and np.linalg.det(coef[:2].T) < 0:
            out[f] = 1
    return out


def _subpix(gray: np.ndarray, pts: np.ndarray, win: int) -> np.ndarray:
    import cv2

    if len(pts) == 0:
        return pts
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 0.001)
    p = np.ascontiguousarray(pts.reshape(-1, 1, 2).astype(np.float32))
    out = cv2.cornerSubPix(gray, p, (win, win), (-1, -1), crit)
    return np.asarray(out, dtype=np.float64).reshape(-1, 2)


def detect_charuco(
    gray: np.ndarray, board: CharucoBoard, detector: cv2.aruco.CharucoDetector | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``(corner ids (N,), corners (N, 2))`` of one ChArUco detection in a (H, W) image.

    Args:
        gray: (H, W) uint8 image.
        board: the board.
        detector: a :func:`charuco_detector` for ``board`` (default: a new one).

    Returns:
        the corner ids and their pixel coordinates (empty when none is found).
    """
    ids, pts, _markers = detect_charuco_markers(gray, board, detector)
    return ids, pts


def detect_charuco_markers(
    gray: np.ndarray, board: CharucoBoard, detector: cv2.aruco.CharucoDetector | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(corner ids (N,), corners (N, 2), marker ids (M,))`` of one ChArUco detection.

    Args:
        gray: (H, W) uint8 image.
        board: the board.
        detector: a :func:`charuco_detector` for ``board`` (default: a new one).

    Returns:
        the corner ids, their pixel coordinates and the ids of the markers found.
    """
    if detector is None:
        detector = charuco_detector(board)
    cc, ci, _mc, mi = detector.detectBoard(gray)
    markers = np.zeros(0, np.int64) if mi is None else np.asarray(mi, np.int64).reshape(-1)
    if ci is None or cc is None or len(ci) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 2)), markers
    return (
        np.asarray(ci, np.int64).reshape(-1),
        np.asarray(cc, np.float64).reshape(-1, 2),
        markers,
    )


def charuco_detector(
    board: CharucoBoard, windows: tuple[int, int] | None = None
) -> cv2.aruco.CharucoDetector:
    """OpenCV ChArUco detector whose markers come from adaptive-threshold windows.

    Its dictionary holds only the board's markers (:func:`board_dictionary`): the same
    detections as with the whole dictionary, faster, since each marker candidate that is not
    a marker (the board's black squares) is compared with every dictionary entry.

    Args:
        board: the board.
        windows: (smallest, largest) adaptive-threshold window (px), step 10 (default
            :data:`CHARUCO_THRESH_WINDOWS`).

    Returns:
        the ``cv2.aruco.CharucoDetector``.
    """
    import cv2

    cp = cv2.aruco.CharucoParameters()
    cp.minMarkers = 2  # a corner needs both neighbouring markers (no edge artefacts)
    dp = cv2.aruco.DetectorParameters()
    # marker candidates from two adaptive-threshold windows (3 and 13 px) instead of OpenCV's
    # three (3, 13, 23), with the same corner accuracy. Bits are read from the image, not from
    # the thresholded one, so large markers are still found: their outline is an edge at any
    # window size.
    dp.adaptiveThreshWinSizeMin, dp.adaptiveThreshWinSizeMax = windows or CHARUCO_THRESH_WINDOWS
    return cv2.aruco.CharucoDetector(board.cv_board(board_markers_only=True), cp, dp)


def detect_chessboard(gray: np.ndarray, board: ChessboardBoard) -> tuple[np.ndarray, np.ndarray]:
    """``(corner ids (N,), corners (N, 2))`` of the chessboard in a (H, W) image.

    Args:
        gray: (H, W) uint8 image.
        board: the board.

    Returns:
        all corners in id order (the grid turned so that corner 0 is next to the black
        corner square), or empty arrays when the board is not found.
    """
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


def aruco_detector(
    dictionary_name: str, border_bits: int = 1, num_markers: int | None = None
) -> cv2.aruco.ArucoDetector:
    """OpenCV marker detector for a named dictionary.

    Args:
        dictionary_name: OpenCV dictionary name (``"DICT_APRILTAG_36h11"``).
        border_bits: width of the markers' black border (cells).
        num_markers: only know ids 0..num_markers-1
            (:func:`~freipose.calibration.boards.board_dictionary`: the same detections of
            those markers, faster); ``None``: the whole dictionary.

    Returns:
        the ``cv2.aruco.ArucoDetector`` (no corner refinement).
    """
    import cv2

    p = cv2.aruco.DetectorParameters()
    p.markerBorderBits = int(border_bits)
    p.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
    if num_markers is None:
        dictionary = get_dictionary(dictionary_name)
    else:
        dictionary = board_dictionary(dictionary_name, num_markers)
    return cv2.aruco.ArucoDetector(dictionary, p)


def detect_aprilgrid(
    gray: np.ndarray, board: AprilGridBoard, detector: cv2.aruco.ArucoDetector | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``(point ids (N,), corners (N, 2))`` of the grid's tag corners in a (H, W) image.

    Args:
        gray: (H, W) uint8 image.
        board: the board.
        detector: an :func:`aruco_detector` for the board's tags (default: a new one).

    Returns:
        the point ids (4 per tag) and their sub-pixel coordinates (empty when none is found).
    """
    pid, pts, _markers, _rejected = detect_aprilgrid_candidates(gray, board, detector)
    return pid, pts


def detect_aprilgrid_candidates(
    gray: np.ndarray, board: AprilGridBoard, detector: cv2.aruco.ArucoDetector | None = None
) -> tuple[np.ndarray, np.ndarray, int, np.ndarray]:
    """:func:`detect_aprilgrid`, with the number of tags found and the rejected candidates.

    Args:
        gray: (H, W) uint8 image.
        board: the board.
        detector: an :func:`aruco_detector` for the board's tags (default: a new one).

    Returns:
        the point ids, their coordinates, the number of the board's tags found and the
        (R, 4, 2) outlines of the marker candidates that decoded to no tag (a mirrored grid
        gives many).
    """
    if detector is None:
        detector = aruco_detector(board.dictionary, board.border, board.n_tags)
    corners, ids, rejected = detector.detectMarkers(gray)
    rejected_quads = quads(rejected)
    if ids is None or len(ids) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 2)), 0, rejected_quads
    ids = np.asarray(ids, np.int64).reshape(-1)
    corners = [np.asarray(c, np.float64).reshape(4, 2) for c in corners]
    keep = ids < board.n_tags
    if not keep.any():
        return np.zeros(0, np.int64), np.zeros((0, 2)), 0, rejected_quads
    ids = ids[keep]
    cs = np.stack([c for c, k in zip(corners, keep) if k])  # (M, 4, 2) TL TR BR BL
    side = np.linalg.norm(cs - np.roll(cs, 1, axis=1), axis=-1).min()
    # the tag corners are X-junctions with the black corner squares: refine on them
    win = int(np.clip(side * board.tag_spacing / 2.5, 2, 9))
    pts = _subpix(gray, cs.reshape(-1, 2), win).reshape(-1, 4, 2)
    order = np.asarray(board.OPENCV_TO_CORNER)
    pid = (4 * ids[:, None] + order[None, :]).reshape(-1)
    return pid, pts.reshape(-1, 2), int(keep.sum()), rejected_quads


def detect_image(image: np.ndarray, board: Board) -> tuple[np.ndarray, np.ndarray]:
    """Detect the board in one image.

    Args:
        image: (H, W, 3) BGR or (H, W) gray uint8.
        board: the board.

    Returns:
        ``(ids (N,) int, corners (N, 2) float64)``: point ids into ``board.object_points`` and
        their pixel coordinates; empty when the board is not found. A ChArUco board or
        AprilTag grid that is not found is searched in the mirror image too (its back seen
        through a transparent print, or a double-sided print's back): what is found there is
        mapped back to this image (see :func:`board_side`).
    """
    import cv2

    gray = board_gray(image, board)
    ids, pts = _detect_gray(gray, board)
    if len(ids) >= 4 or isinstance(board, ChessboardBoard):
        return ids, pts
    ids_m, pts_m = _detect_gray(cv2.flip(gray, 1), board)
    if len(ids_m) >= 4:
        return ids_m, mirror_x(pts_m, gray.shape[1])
    return ids, pts


def _detect_gray(gray: np.ndarray, board: Board) -> tuple[np.ndarray, np.ndarray]:
    """``(ids, corners)`` of the board printed dark on light in a (H, W) gray image."""
    if isinstance(board, CharucoBoard):
        return detect_charuco(gray, board)
    if isinstance(board, ChessboardBoard):
        return detect_chessboard(gray, board)
    if isinstance(board, AprilGridBoard):
        return detect_aprilgrid(gray, board)
    raise TypeError(f"unsupported board {type(board).__name__}")
