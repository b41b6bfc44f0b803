"""Calibration boards: ChArUco, chessboard and FreiCalib/Kalibr AprilTag grids.

Every board is a frozen dataclass with

* ``size_mm`` -> ``(width_mm, height_mm)``: the physical extent of the printed pattern;
* ``texture(px_per_mm)`` -> uint8 ``(H, W)`` grayscale image of exactly that extent (white
  background, black pattern, anti-aliased; its negative for a board with ``inverted = true``),
  as it is printed and as the synthetic renderer maps it onto the board plane;
* ``object_points`` -> ``(P, 3)`` float64 board-frame coordinates (mm, z = 0) of every detectable
  corner, in id order;
* ``to_dict()`` which round-trips through
  :func:`freipose.calibration.board_files.board_from_dict`.

Board frame: the board plane is z = 0, x runs along the texture's columns (right), y along its
rows (down); board point ``(x, y, 0)`` mm is texture pixel ``(x * px_per_mm - 0.5,
y * px_per_mm - 0.5)`` (pixel-centre convention), i.e. the texture's top-left pixel *edge* is the
origin. z = x × y points into the board, away from a camera that sees the printed side.

Board files (TOML, JSON, FreiCalib marker JSON) are read and written by
:mod:`freipose.calibration.board_files`.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import numpy as np

from freipose.errors import FreiPoseError

if TYPE_CHECKING:  # OpenCV is imported where it is used
    import cv2

__all__ = [
    "AprilGridBoard",
    "Board",
    "BoardError",
    "CharucoBoard",
    "ChessboardBoard",
    "board_dictionary",
    "board_hash",
    "get_dictionary",
]


class BoardError(FreiPoseError):
    """A board description is missing a field, has an invalid value or cannot be read."""


# --------------------------------------------------------------------------------------------
# dictionaries


_APRILTAG_FAMILIES: Mapping[str, str] = MappingProxyType(
    {
        "16h5": "DICT_APRILTAG_16h5",
        "25h9": "DICT_APRILTAG_25h9",
        "36h10": "DICT_APRILTAG_36h10",
        "36h11": "DICT_APRILTAG_36h11",
    }
)


def _normalize_dictionary_name(name: str) -> str:
    """``"4x4_50"``, ``"DICT_4X4_50"``, ``"dict_aruco_original"`` -> canonical OpenCV name."""
    import cv2

    raw = str(name).strip()
    candidates = [raw, raw.upper(), "DICT_" + raw.upper()]
    for fam, dict_name in _APRILTAG_FAMILIES.items():
        if raw.lower() in (fam, "tag" + fam, "t" + fam, dict_name.lower()):
            return dict_name
    for cand in candidates:
        if cand.startswith("DICT_") and hasattr(cv2.aruco, cand):
            return cand
    known = sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_"))
    raise BoardError(
        f"unknown marker dictionary {name!r}; expected an OpenCV name such as "
        f"'DICT_4X4_50' (known: {', '.join(known)})"
    )


def get_dictionary(name: str) -> cv2.aruco.Dictionary:
    """The ``cv2.aruco.Dictionary`` for an OpenCV dictionary name (``"DICT_4X4_50"``)."""
    import cv2

    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, _normalize_dictionary_name(name)))


def board_dictionary(name: str, num_markers: int) -> cv2.aruco.Dictionary:
    """The first ``num_markers`` markers of a named dictionary, as a ``cv2.aruco.Dictionary``.

    They are the markers a board with ids 0..num_markers-1 uses, with the named dictionary's
    error correction. OpenCV identifies a marker candidate as the *first* dictionary entry
    within its error correction, so a detector with this dictionary reports exactly the
    board's markers that one with the whole dictionary reports, and drops the markers of other
    boards. It is faster: most candidates are not markers (a ChArUco board's black squares),
    and each of them is compared with every entry before it is rejected.

    Args:
        name: the dictionary's name (see :func:`get_dictionary`).
        num_markers: how many of its first markers to keep.

    Returns:
        the smaller dictionary.
    """
    import cv2

    full = get_dictionary(name)
    n = min(int(num_markers), len(full.bytesList))
    return cv2.aruco.Dictionary(full.bytesList[:n].copy(), full.markerSize, full.maxCorrectionBits)


def _marker_bits(dictionary_name: str, marker_id: int, border_bits: int = 1) -> np.ndarray:
    """(n, n) bool array, True = black, of one marker including its black border."""
    import cv2

    d = get_dictionary(dictionary_name)
    n = d.markerSize + 2 * border_bits
    img = cv2.aruco.generateImageMarker(d, int(marker_id), n, borderBits=border_bits)
    return np.asarray(img) < 128


# --------------------------------------------------------------------------------------------
# rasterization


def _rasterize(
    width_mm: float,
    height_mm: float,
    px_per_mm: float,
    black: Callable[[np.ndarray, np.ndarray], np.ndarray],
    supersample: int = 4,
) -> np.ndarray:
    """Anti-aliased texture: each pixel averages ``supersample**2`` point samples of ``black``."""
    if not (px_per_mm > 0 and math.isfinite(px_per_mm)):
        raise BoardError(f"px_per_mm must be a positive number, got {px_per_mm}")
    w = int(round(width_mm * px_per_mm))
    h = int(round(height_mm * px_per_mm))
    if w < 1 or h < 1:
        raise BoardError(
            f"px_per_mm={px_per_mm} gives an empty texture for a {width_mm}x{height_mm} mm board"
        )
    if w * h > 40000 * 40000:
        raise BoardError(f"texture of {w}x{h} px is too large; lower px_per_mm")
    ss = int(supersample)
    offs = (np.arange(ss) + 0.5) / ss  # sub-sample offsets inside a pixel, in pixel units
    xs = ((np.arange(w)[:, None] + offs[None, :]) / px_per_mm).ravel()  # (w*ss,)
    out = np.empty((h, w), dtype=np.uint8)
    rows_per_chunk = max(1, int(4_000_000 // max(1, w * ss * ss)))
    for r0 in range(0, h, rows_per_chunk):
        r1 = min(h, r0 + rows_per_chunk)
        ys = ((np.arange(r0, r1)[:, None] + offs[None, :]) / px_per_mm).ravel()
        blk = black(xs[None, :], ys[:, None])  # (rows*ss, w*ss) bool
        frac = blk.reshape(r1 - r0, ss, w, ss).mean(axis=(1, 3))
        out[r0:r1] = np.round(255.0 * (1.0 - frac)).astype(np.uint8)
    return out


def _all_marker_bits(dictionary_name: str, count: int, border_bits: int) -> np.ndarray:
    """(count, n, n) bool cell grids (True = black) of markers 0..count-1."""
    return np.stack([_marker_bits(dictionary_name, i, border_bits) for i in range(count)])


def require_positive_int(name: str, value: Any, minimum: int = 1) -> int:
    """``value`` as an int, when it is a whole number >= ``minimum``; ``name`` is for messages.

    Raises:
        BoardError: ``value`` is no whole number or is below ``minimum``.
    """
    if isinstance(value, bool) or not isinstance(value, (int, np.integer, float)):
        raise BoardError(f"{name} must be an integer >= {minimum}, got {value!r}")
    if float(value) != int(value) or int(value) < minimum:
        raise BoardError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def require_positive(name: str, value: Any) -> float:
    """``value`` as a float, when it is a finite positive number; ``name`` is for messages.

    Raises:
        BoardError: ``value`` is no positive finite number.
    """
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise BoardError(f"{name} must be a positive number (mm), got {value!r}")
    if not (float(value) > 0 and math.isfinite(float(value))):
        raise BoardError(f"{name} must be a positive number (mm), got {value!r}")
    return float(value)


def require_bool(name: str, value: Any) -> bool:
    """``value`` when it is a boolean (``true``/``false`` in TOML); ``name`` is for messages.

    Raises:
        BoardError: ``value`` is no boolean.
    """
    if not isinstance(value, (bool, np.bool_)):
        raise BoardError(f"{name} must be true or false, got {value!r}")
    return bool(value)


def _print(tex: np.ndarray, inverted: bool) -> np.ndarray:
    """The texture as printed: white on black (the negative) for an inverted board."""
    return 255 - tex if inverted else tex


def _fields_dict(kind: str, board: Any) -> dict[str, Any]:
    """``type`` and the board's fields, ``inverted`` only when true (normal boards' hash stays)."""
    d = {"type": kind, **asdict(board)}
    if not d.get("inverted"):
        d.pop("inverted", None)
    return d


# --------------------------------------------------------------------------------------------
# ChArUco


@dataclass(frozen=True)
class CharucoBoard:
    """ChArUco board of ``squares_x`` x ``squares_y`` squares (OpenCV layout).

    The top-left square is black (OpenCV >= 4.6); with ``legacy_pattern`` and an even number of
    rows it is white instead (boards printed by OpenCV < 4.6 or aniposelib). Markers sit centred
    in the white squares with ids in row-major order. Corner ids are row-major over the
    ``(squares_x - 1) x (squares_y - 1)`` inner corners. ``inverted``: printed as the negative.
    """

    squares_x: int
    squares_y: int
    square_size: float
    marker_size: float
    dictionary: str
    legacy_pattern: bool = False
    inverted: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "squares_x", require_positive_int("squares_x", self.squares_x, 2))
        object.__setattr__(self, "squares_y", require_positive_int("squares_y", self.squares_y, 2))
        object.__setattr__(self, "square_size", require_positive("square_size", self.square_size))
        object.__setattr__(self, "marker_size", require_positive("marker_size", self.marker_size))
        if self.marker_size >= self.square_size:
            raise BoardError(
                f"marker_size ({self.marker_size} mm) must be smaller than square_size "
                f"({self.square_size} mm)"
            )
        object.__setattr__(self, "dictionary", _normalize_dictionary_name(self.dictionary))
        object.__setattr__(self, "legacy_pattern", bool(self.legacy_pattern))
        object.__setattr__(self, "inverted", require_bool("inverted", self.inverted))
        n_markers = (self.squares_x * self.squares_y) // 2
        available = get_dictionary(self.dictionary).bytesList.shape[0]
        if n_markers > available:
            raise BoardError(
                f"a {self.squares_x}x{self.squares_y} ChArUco board needs {n_markers} markers "
                f"but {self.dictionary} has only {available}; use a larger dictionary"
            )

    kind = "charuco"

    @property
    def size_mm(self) -> tuple[float, float]:
        """(width, height) mm of the printed pattern."""
        return (self.squares_x * self.square_size, self.squares_y * self.square_size)

    @property
    def n_markers(self) -> int:
        """Number of markers (ids 0..n_markers-1)."""
        return (self.squares_x * self.squares_y) // 2

    @property
    def first_square_black(self) -> bool:
        """Whether square (row 0, col 0) is black."""
        return not (self.legacy_pattern and self.squares_y % 2 == 0)

    def square_is_black(self, col: np.ndarray, row: np.ndarray) -> np.ndarray:
        """Whether square (col, row) is black, elementwise."""
        even = (np.asarray(col) + np.asarray(row)) % 2 == 0
        return even if self.first_square_black else ~even

    def marker_squares(self) -> np.ndarray:
        """(M, 2) int (col, row) of the square holding marker id m, in id order."""
        grid_cols, grid_rows = np.meshgrid(np.arange(self.squares_x), np.arange(self.squares_y))
        cols, rows = grid_cols.ravel(), grid_rows.ravel()  # row-major
        white = ~self.square_is_black(cols, rows)
        return np.stack([cols[white], rows[white]], axis=1)

    @property
    def object_points(self) -> np.ndarray:
        """(P, 3) board-frame coordinates (mm, z = 0) of the inner corners, in id order."""
        s = self.square_size
        gx, gy = np.meshgrid(np.arange(1, self.squares_x), np.arange(1, self.squares_y))
        pts = np.stack([gx.ravel() * s, gy.ravel() * s, np.zeros(gx.size)], axis=1)
        return pts.astype(np.float64)

    def marker_corners_mm(self) -> np.ndarray:
        """(M, 4, 3) board-frame corners of every marker (TL, TR, BR, BL as OpenCV orders)."""
        sq = self.marker_squares().astype(np.float64)
        off = (self.square_size - self.marker_size) / 2
        x0 = sq[:, 0] * self.square_size + off
        y0 = sq[:, 1] * self.square_size + off
        m = self.marker_size
        c = np.stack(
            [
                np.stack([x0, y0], -1),
                np.stack([x0 + m, y0], -1),
                np.stack([x0 + m, y0 + m], -1),
                np.stack([x0, y0 + m], -1),
            ],
            axis=1,
        )
        return np.concatenate([c, np.zeros(c.shape[:2] + (1,))], axis=2)

    def _black(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        s = self.square_size
        shape = np.broadcast_shapes(x.shape, y.shape)
        xb = np.broadcast_to(x, shape)
        yb = np.broadcast_to(y, shape)
        col = np.floor(xb / s).astype(np.int64)
        row = np.floor(yb / s).astype(np.int64)
        out = self.square_is_black(col, row)
        lut = np.full((self.squares_y, self.squares_x), -1, dtype=np.int64)
        sq = self.marker_squares()
        lut[sq[:, 1], sq[:, 0]] = np.arange(len(sq))
        inb = (col >= 0) & (col < self.squares_x) & (row >= 0) & (row < self.squares_y)
        mid = np.where(
            inb, lut[np.clip(row, 0, self.squares_y - 1), np.clip(col, 0, self.squares_x - 1)], -1
        )
        bits = _all_marker_bits(self.dictionary, len(sq), 1)
        n = bits.shape[1]
        off = (s - self.marker_size) / 2
        cell = self.marker_size / n
        u = np.floor((xb - col * s - off) / cell).astype(np.int64)
        v = np.floor((yb - row * s - off) / cell).astype(np.int64)
        inside = (mid >= 0) & (u >= 0) & (u < n) & (v >= 0) & (v < n)
        vals = bits[np.maximum(mid, 0), np.clip(v, 0, n - 1), np.clip(u, 0, n - 1)]
        return np.where(inside, vals, out & inb)

    def texture(self, px_per_mm: float) -> np.ndarray:
        """(H, W) uint8 print at ``px_per_mm`` (anti-aliased; the negative when ``inverted``)."""
        w, h = self.size_mm
        return _print(_rasterize(w, h, px_per_mm, self._black), self.inverted)

    def cv_board(self, *, board_markers_only: bool = False) -> cv2.aruco.CharucoBoard:
        """The equivalent ``cv2.aruco.CharucoBoard`` (lengths in mm).

        Args:
            board_markers_only: its dictionary holds only the board's markers (for
                detection: the same detections, faster; see :func:`board_dictionary`).

        Returns:
            the OpenCV board.
        """
        import cv2

        if board_markers_only:
            dictionary = board_dictionary(self.dictionary, self.n_markers)
        else:
            dictionary = get_dictionary(self.dictionary)
        b = cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y),
            float(self.square_size),
            float(self.marker_size),
            dictionary,
        )
        b.setLegacyPattern(self.legacy_pattern)
        return b

    def to_dict(self) -> dict[str, Any]:
        """The fields, with ``type``, that ``board_from_dict`` reads back."""
        return _fields_dict("charuco", self)


# --------------------------------------------------------------------------------------------
# chessboard


@dataclass(frozen=True)
class ChessboardBoard:
    """Chessboard with ``inner_corners_x`` x ``inner_corners_y`` inner corners.

    The printed pattern has a white quiet zone of one square around the squares (the chessboard
    detector needs it), so ``size_mm`` = ``(inner_corners + 3) * square_size``. The top-left square
    is black; corner ids are row-major (``inner_corners_x`` per row). ``inverted``: printed as
    the negative (a black quiet zone, white squares where the normal print has black ones).
    """

    inner_corners_x: int
    inner_corners_y: int
    square_size: float
    inverted: bool = False

    kind = "chessboard"

    def __post_init__(self) -> None:
        n = require_positive_int("inner_corners_x", self.inner_corners_x, 2)
        object.__setattr__(self, "inner_corners_x", n)
        n = require_positive_int("inner_corners_y", self.inner_corners_y, 2)
        object.__setattr__(self, "inner_corners_y", n)
        object.__setattr__(self, "square_size", require_positive("square_size", self.square_size))
        object.__setattr__(self, "inverted", require_bool("inverted", self.inverted))

    @property
    def margin_mm(self) -> float:
        """Width (mm) of the white quiet zone around the squares."""
        return self.square_size

    @property
    def size_mm(self) -> tuple[float, float]:
        """(width, height) mm of the printed pattern, quiet zone included."""
        s = self.square_size
        return (
            (self.inner_corners_x + 1) * s + 2 * self.margin_mm,
            (self.inner_corners_y + 1) * s + 2 * self.margin_mm,
        )

    @property
    def object_points(self) -> np.ndarray:
        """(P, 3) board-frame coordinates (mm, z = 0) of the inner corners, in id order."""
        s, m = self.square_size, self.margin_mm
        gx, gy = np.meshgrid(
            np.arange(1, self.inner_corners_x + 1), np.arange(1, self.inner_corners_y + 1)
        )
        return np.stack([m + gx.ravel() * s, m + gy.ravel() * s, np.zeros(gx.size)], axis=1)

    def _black(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        s, m = self.square_size, self.margin_mm
        col = np.floor((x - m) / s)
        row = np.floor((y - m) / s)
        inside = (
            (col >= 0) & (col <= self.inner_corners_x) & (row >= 0) & (row <= self.inner_corners_y)
        )
        return inside & ((col + row) % 2 == 0)

    def texture(self, px_per_mm: float) -> np.ndarray:
        """(H, W) uint8 print at ``px_per_mm`` (anti-aliased; the negative when ``inverted``)."""
        w, h = self.size_mm
        return _print(_rasterize(w, h, px_per_mm, self._black), self.inverted)

    def to_dict(self) -> dict[str, Any]:
        """The fields, with ``type``, that ``board_from_dict`` reads back."""
        return _fields_dict("chessboard", self)


# --------------------------------------------------------------------------------------------
# AprilTag grid (Kalibr / FreiCalib)


@dataclass(frozen=True)
class AprilGridBoard:
    """Kalibr-style AprilTag grid as printed by FreiCalib's ``create_marker.py``.

    ``tags_x`` x ``tags_y`` tags of ``tag_size`` mm (outer edge of the black border, ``border``
    bits wide), separated by ``tag_spacing * tag_size`` mm, with black squares of that size at
    every gap intersection (also on the outside). Tag ids are row-major from the *bottom-left*
    tag of the print (Kalibr layout); point id = 4 * tag_id + corner, corners counter-clockwise
    on the print starting bottom-left (FreiCalib's order). Only the front side of double-sided
    boards is used.
    """

    tags_x: int
    tags_y: int
    tag_size: float
    tag_spacing: float
    family: str = "36h11"
    border: int = 2
    inverted: bool = False

    kind = "aprilgrid"

    def __post_init__(self) -> None:
        object.__setattr__(self, "tags_x", require_positive_int("tags_x", self.tags_x, 1))
        object.__setattr__(self, "tags_y", require_positive_int("tags_y", self.tags_y, 1))
        object.__setattr__(self, "tag_size", require_positive("tag_size", self.tag_size))
        sp = require_positive("tag_spacing", self.tag_spacing)
        if sp >= 2.0:
            raise BoardError(
                f"tag_spacing is a fraction of tag_size (FreiCalib default 0.25), got {sp}"
            )
        object.__setattr__(self, "tag_spacing", sp)
        fam = str(self.family).strip().lower()
        for prefix in ("dict_apriltag_", "tag", "t"):
            if fam.startswith(prefix) and fam[len(prefix) :] in _APRILTAG_FAMILIES:
                fam = fam[len(prefix) :]
        if fam not in _APRILTAG_FAMILIES:
            raise BoardError(
                f"unknown AprilTag family {self.family!r}; expected one of "
                f"{', '.join(_APRILTAG_FAMILIES)}"
            )
        object.__setattr__(self, "family", fam)
        object.__setattr__(self, "border", require_positive_int("border", self.border, 1))
        object.__setattr__(self, "inverted", require_bool("inverted", self.inverted))
        available = get_dictionary(self.dictionary).bytesList.shape[0]
        if self.tags_x * self.tags_y > available:
            raise BoardError(
                f"{self.tags_x * self.tags_y} tags needed but tag{fam} has only {available}"
            )

    @property
    def dictionary(self) -> str:
        """The OpenCV dictionary name of the tag family."""
        return _APRILTAG_FAMILIES[self.family]

    @property
    def spacing_mm(self) -> float:
        """Gap (mm) between neighbouring tags."""
        return self.tag_spacing * self.tag_size

    @property
    def size_mm(self) -> tuple[float, float]:
        """(width, height) mm of the printed pattern."""
        sp = self.spacing_mm
        return (self.tags_x * (self.tag_size + sp) + sp, self.tags_y * (self.tag_size + sp) + sp)

    @property
    def n_tags(self) -> int:
        """Number of tags (ids 0..n_tags-1)."""
        return self.tags_x * self.tags_y

    def tag_origins(self) -> np.ndarray:
        """(T, 2) top-left (x, y) mm of every tag in id order."""
        t = np.arange(self.n_tags)
        col = t % self.tags_x
        row_from_bottom = t // self.tags_x
        row = self.tags_y - 1 - row_from_bottom
        pitch = self.tag_size + self.spacing_mm
        return np.stack([self.spacing_mm + col * pitch, self.spacing_mm + row * pitch], axis=1)

    def tag_corners_mm(self) -> np.ndarray:
        """(T, 4, 3) tag corners in FreiCalib order (print: BL, BR, TR, TL)."""
        o = self.tag_origins()
        s = self.tag_size
        x0, y0 = o[:, 0], o[:, 1]
        c = np.stack(
            [
                np.stack([x0, y0 + s], -1),
                np.stack([x0 + s, y0 + s], -1),
                np.stack([x0 + s, y0], -1),
                np.stack([x0, y0], -1),
            ],
            axis=1,
        )
        return np.concatenate([c, np.zeros(c.shape[:2] + (1,))], axis=2)

    # OpenCV returns marker corners TL, TR, BR, BL: FreiCalib corner index = 3 - OpenCV index.
    OPENCV_TO_CORNER = (3, 2, 1, 0)

    @property
    def object_points(self) -> np.ndarray:
        """The fields, with ``type``, that ``board_from_dict`` reads back."""
        return self.tag_corners_mm().reshape(-1, 3).astype(np.float64)

    def _black(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        sp, s = self.spacing_mm, self.tag_size
        pitch = s + sp
        shape = np.broadcast_shapes(x.shape, y.shape)
        xb = np.broadcast_to(x, shape)
        yb = np.broadcast_to(y, shape)
        out = (np.mod(xb, pitch) < sp) & (np.mod(yb, pitch) < sp)  # gap-intersection squares
        col = np.floor((xb - sp) / pitch).astype(np.int64)
        row = np.floor((yb - sp) / pitch).astype(np.int64)
        inb = (col >= 0) & (col < self.tags_x) & (row >= 0) & (row < self.tags_y)
        tid = (self.tags_y - 1 - row) * self.tags_x + col
        bits = _all_marker_bits(self.dictionary, self.n_tags, self.border)
        n = bits.shape[1]
        cell = s / n
        u = np.floor((xb - sp - col * pitch) / cell).astype(np.int64)
        v = np.floor((yb - sp - row * pitch) / cell).astype(np.int64)
        inside = inb & (u >= 0) & (u < n) & (v >= 0) & (v < n)
        vals = bits[np.clip(tid, 0, self.n_tags - 1), np.clip(v, 0, n - 1), np.clip(u, 0, n - 1)]
        return np.where(inside, vals, out)

    def texture(self, px_per_mm: float) -> np.ndarray:
        """(H, W) uint8 print at ``px_per_mm`` (anti-aliased; the negative when ``inverted``)."""
        w, h = self.size_mm
        return _print(_rasterize(w, h, px_per_mm, self._black), self.inverted)

    def to_dict(self) -> dict[str, Any]:
        """The fields, with ``type``, that ``board_from_dict`` reads back."""
        return _fields_dict("aprilgrid", self)


Board = CharucoBoard | ChessboardBoard | AprilGridBoard


def board_hash(board: Board) -> str:
    """Short stable hash of the board's definition (for detection caches)."""
    text = json.dumps(board.to_dict(), sort_keys=True)
    return hashlib.sha1(text.encode()).hexdigest()[:12]
