"""Atomic file output: write to a temporary name in the same folder, rename on success."""

from __future__ import annotations

import contextlib
import os
import re
import tempfile
from collections.abc import Iterator
from pathlib import Path

from freipose.errors import FreiPoseError

# The process umask, read once: mkstemp creates 0600 files, but outputs should get the
# permissions an ordinary open() would give them (0666 & ~umask).
_UMASK = os.umask(0o022)
os.umask(_UMASK)


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; move it onto ``path`` only if the block succeeds.

    A failure (exception, kill) never leaves a half-written file under the final name.
    The temporary file keeps the final suffix so that libraries choosing a format by
    suffix (OpenCV, matplotlib) still work.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sfx = path.suffix if suffix is None else suffix
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".partial{sfx}", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        try:
            mode = path.stat().st_mode & 0o777 if path.exists() else 0o666 & ~_UMASK
            os.chmod(tmp_path, mode)
        except OSError:  # e.g. a filesystem without permissions; the data still counts
            pass
        os.replace(tmp_path, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (UTF-8)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


class OutputExistsError(FreiPoseError):
    """An output that exists would be replaced without ``--overwrite``."""


def refuse_existing(path: str | Path, overwrite: bool) -> None:
    """Refuse to replace the existing output ``path`` unless ``overwrite``.

    Raises:
        OutputExistsError: ``path`` exists and ``overwrite`` is false.
    """
    if Path(path).exists() and not overwrite:
        raise OutputExistsError(f"{path} exists; pass --overwrite to replace it")


def leftover_partials(path: str | Path, suffix: str | None = None) -> list[Path]:
    """Temporary files of :func:`atomic_path` for ``path`` left by a killed run.

    They lie next to ``path`` and are named ``.<stem>.<random>.partial<suffix>``; the
    name ``.<stem>.partial<suffix>`` (the temporary file of
    :class:`freipose.io.video.VideoWriter`) counts too.
    """
    path = Path(path)
    sfx = path.suffix if suffix is None else suffix
    if not path.parent.is_dir():
        return []
    pattern = re.compile(
        re.escape(f".{path.stem}.") + r"([a-z0-9_]{8}\.)?" + re.escape(f"partial{sfx}") + "$"
    )
    return sorted(p for p in path.parent.iterdir() if pattern.match(p.name) and p.is_file())


def remove_leftover_partials(path: str | Path, suffix: str | None = None) -> list[Path]:
    """Delete the :func:`leftover_partials` of ``path``; returns the files removed.

    Call it only while holding the output's lock, so that no other run is writing them.
    """
    removed = []
    for p in leftover_partials(path, suffix):
        with contextlib.suppress(FileNotFoundError):
            p.unlink()
            removed.append(p)
    return removed
