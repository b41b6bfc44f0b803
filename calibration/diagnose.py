"""Diagnosis of a board that is never found: which board do the images probably show?"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from freipose.calibration.boards import (
    AprilGridBoard,
    Board,
    CharucoBoard,
    ChessboardBoard,
    get_dictionary,
)
from freipose.calibration.detect import aruco_detector, board_gray, detect_charuco, detect_image

__all__ = ["diagnose_board"]


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
    """Number of markers in the named dictionary."""
    return int(get_dictionary(name).bytesList.shape[0])


def _smallest_family_member(name: str, max_id: int) -> str:
    """The smallest dictionary of ``name``'s family (4X4_50 ... 4X4_1000) with ``max_id``."""
    import cv2

    parts = name.split("_")
    if len(parts) == 3 and parts[2] == "1000":
        for size in (50, 100, 250, 1000):
            cand = f"{parts[0]}_{parts[1]}_{size}"
            if hasattr(cv2.aruco, cand) and max_id < size:
                return cand
    return name


def _inversion_hint(images: Sequence[np.ndarray], board: Board, board_file: str) -> str | None:
    """A sentence when the board is found with the other ``inverted`` setting, else ``None``."""
    other = replace(board, inverted=not board.inverted)
    n = sum(len(detect_image(im, other)[0]) for im in images)
    if n < 4:
        return None
    if other.inverted:
        return (
            f"the board looks inverted (white pattern on black: {n} corners found in the "
            f"negative images): add `inverted = true` to {board_file}"
        )
    return (
        f"the board looks like a normal print (dark pattern on white: {n} corners found), but "
        f"{board_file} says inverted = true: remove that line"
    )


def diagnose_board(
    images: Sequence[np.ndarray], board: Board, board_file: str | None = None
) -> str:
    """Explain why ``board`` is not found in ``images`` by trying other boards.

    Tries the board with the other ``inverted`` setting (a print's negative), every OpenCV
    marker dictionary (1- and 2-bit borders), the legacy ChArUco layout and other ChArUco
    sizes.

    Args:
        images: (H, W, 3) BGR or (H, W) gray frames of one camera.
        board: the board that was not found.
        board_file: the board's file, for the message (default: "the board file").

    Returns:
        a sentence for the user.
    """
    inverted = _inversion_hint(images, board, board_file or "the board file")
    if inverted is not None:
        return inverted
    grays = [board_gray(im, board) for im in images]
    # 1. markers of which dictionary?
    found: dict[tuple[str, int], tuple[int, int]] = {}  # (dict, border) -> (count, max id)
    for dname, border in _probe_dictionaries():
        det = aruco_detector(dname, border)
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
        return _charuco_hint(grays, board, dname, count, max_id)
    return (
        f"{count} {dname} markers were found (ids up to {max_id}) but no board corners; "
        f"check tags_x/tags_y"
    )


def _charuco_hint(
    grays: list[np.ndarray], board: CharucoBoard, dname: str, count: int, max_id: int
) -> str:
    """What is wrong with a ChArUco board whose markers are found but not its corners.

    Args:
        grays: (H, W) gray frames.
        board: the configured board (of the right dictionary).
        dname: the dictionary.
        count: markers found.
        max_id: the largest marker id found.

    Returns:
        a sentence for the user: a layout that finds corners, or what to check.
    """
    hints: list[str] = []
    if max_id >= board.n_markers:
        hints.append(
            f"markers with ids up to {max_id} were found but a {board.squares_x}x"
            f"{board.squares_y} board has only ids 0..{board.n_markers - 1}: "
            "the board is larger"
        )
    alt = []
    for sx, sy, legacy in _charuco_candidates(board, max_id):
        cand = CharucoBoard(sx, sy, board.square_size, board.marker_size, board.dictionary, legacy)
        n = sum(len(detect_charuco(g, cand)[0]) for g in grays)
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


def _charuco_candidates(board: CharucoBoard, max_id: int) -> list[tuple[int, int, bool]]:
    """Plausible ChArUco layouts ``(squares_x, squares_y, legacy)`` for the marker ids seen.

    They are the transposed board, the other legacy setting, and sizes whose marker count
    just covers the largest id.
    """
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
