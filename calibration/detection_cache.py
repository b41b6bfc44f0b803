"""The on-disk cache of detections: one ``.npz`` per camera, keyed by video and board."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from freipose.calibration.boards import Board, board_hash
from freipose.errors import InputFileError

__all__ = ["CACHE_VERSION", "cache_file", "load_cache", "save_cache"]

CACHE_VERSION = 4  # raised whenever the detections of the same frames change


def _source_signature(path: Path) -> str:
    """Hash of the absolute path, size and modification time (files) or listing (folders).

    Raises:
        InputFileError: a folder entry that does not exist (a broken link).
    """
    p = path.resolve()
    h = hashlib.sha1(str(p).encode())
    if p.is_dir():
        for f in sorted(p.iterdir()):
            try:
                st = f.stat()
            except FileNotFoundError:  # a link to nothing, or a file removed meanwhile
                raise InputFileError(
                    f"{f}: a broken link (or a file removed meanwhile) in the image folder "
                    f"{path}; remove it or make it point to the image"
                ) from None
            h.update(f"{f.name}:{st.st_size}:{st.st_mtime_ns}".encode())
    else:
        st = p.stat()
        h.update(f"{st.st_size}:{st.st_mtime_ns}".encode())
    return h.hexdigest()[:12]


def cache_file(cache_dir: Path, source: Path, board: Board) -> Path:
    """Cache path for one camera's detections: ``<stem>-<video hash>-<board hash>.npz``."""
    name = source.stem if source.is_file() else source.name
    return Path(cache_dir) / f"{name}-{_source_signature(source)}-{board_hash(board)}.npz"


def load_cache(path: Path, num_frames: int, num_points: int) -> np.ndarray | None:
    """One camera's cached (F, P, 2) detections; ``None`` when unreadable, stale or mis-shaped.

    Args:
        path: the cache file (see :func:`cache_file`).
        num_frames: F, the source's frames.
        num_points: P, the board's points.

    Returns:
        the detections, or ``None`` when the file is not a cache of this version and shape.
    """
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


def save_cache(path: Path, points: np.ndarray) -> None:
    """Write one camera's (F, P, 2) detections to the cache file ``path`` atomically."""
    from freipose.io.atomic import atomic_path

    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, points=points, version=np.int64(CACHE_VERSION))
