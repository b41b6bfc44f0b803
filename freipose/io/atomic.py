"""Atomic file output: write to a temporary name in the same folder, rename on success."""

from __future__ import annotations

import contextlib
import errno
import io
import os
import re
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from freipose.errors import FreiPoseError, OutputWriteError, filesystem_message

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

    A full disk or a folder that cannot be written raises :class:`OutputWriteError` that
    names ``path`` (not the temporary name), whether it happens on creating the temporary
    file, in the block (an ``OSError`` about the temporary file or about no file) or on the
    rename.
    """
    path = Path(path)
    sfx = path.suffix if suffix is None else suffix
    with output_errors(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(
            prefix=f".{path.stem}.", suffix=f".partial{sfx}", dir=path.parent
        )
        os.close(fd)
    tmp_path = Path(tmp)
    try:
        with output_errors(path, tmp_path):
            yield tmp_path
        try:
            mode = path.stat().st_mode & 0o777 if path.exists() else 0o666 & ~_UMASK
            os.chmod(tmp_path, mode)
        except OSError:  # e.g. a filesystem without permissions; the data still counts
            pass
        with output_errors(path, tmp_path):
            os.replace(tmp_path, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


@contextlib.contextmanager
def output_errors(path: str | Path, *also: str | Path) -> Iterator[None]:
    """Raise a full disk or a read-only folder met in the block as :class:`OutputWriteError`.

    The message (:func:`~freipose.errors.filesystem_message`) names ``path``. Only errors
    about ``path``, one of ``also``, a file beside ``path`` (its temporary file), a folder
    above it, or no file are turned; one about another file (an input that cannot be read)
    passes unchanged.
    """
    try:
        yield
    except OutputWriteError:
        raise
    except OSError as exc:
        if exc.filename is not None and not _about(Path(path), Path(exc.filename), also):
            raise
        err = OSError(exc.errno, exc.strerror, os.fspath(path))
        msg = filesystem_message(err)
        if msg is None:
            raise
        raise OutputWriteError(msg, exc.errno, path) from exc


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


def _about(path: Path, other: Path, also: tuple[str | Path, ...]) -> bool:
    """Whether ``other`` is ``path``, one of ``also``, its temporary file, or a folder above it."""
    p, o = path.absolute(), other.absolute()
    return (
        o == p
        or (o.parent == p.parent and o.name.startswith(f".{p.stem}."))
        or o in p.parents
        or any(o == Path(a).absolute() for a in also)
    )


class _WriteGuard(io.RawIOBase):
    """A file that never reports a failed write: from the first it keeps writes in memory.

    HDF5 that sees a write fail (a full disk) keeps metadata it can never write and
    crashes the process when the file or the library is closed. Writing through this
    object, HDF5 sees every write succeed: the first failed write is recorded in
    :attr:`error`, and it and every later write are kept in memory (reads see them), so
    HDF5 stays consistent until the owner gives up the file, which is damaged on disk.
    """

    def __init__(self, path: Path, mode: str) -> None:
        super().__init__()
        self._f = io.FileIO(path, mode)  # unbuffered; closed in close()
        self.error: OSError | None = None
        self._kept: list[tuple[int, bytes]] = []  # (offset, data) of writes not on disk

    def readable(self) -> bool:  # noqa: D102
        return True

    def writable(self) -> bool:  # noqa: D102
        return True

    def seekable(self) -> bool:  # noqa: D102
        return True

    def readinto(self, b: Any) -> int:  # noqa: D102
        pos = self._f.tell()
        n = self._f.readinto(b) or 0
        if not self._kept:
            return n
        view = memoryview(b).cast("B")
        view[n:] = bytes(len(view) - n)
        end = n
        for off, data in self._kept:  # in write order: later writes win
            a, z = max(off, pos), min(off + len(data), pos + len(view))
            if a < z:
                view[a - pos : z - pos] = data[a - off : z - off]
                end = max(end, z - pos)
        self._f.seek(pos + end)
        return end

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:  # noqa: D102
        return self._f.seek(offset, whence)

    def tell(self) -> int:  # noqa: D102
        return self._f.tell()

    def write(self, b: Any) -> int:  # noqa: D102
        view = memoryview(b).cast("B")
        n = len(view)
        pos = self._f.tell()
        if self.error is None:
            try:
                done = 0
                while done < n:
                    w = self._f.write(view[done:])
                    if not w:
                        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                    done += w
                return n
            except OSError as exc:
                self.error = exc
        self._kept.append((pos, bytes(view)))
        self._f.seek(pos + n)
        return n

    def truncate(self, size: int | None = None) -> int:  # noqa: D102
        if self.error is None:
            try:
                return self._f.truncate(size)
            except OSError as exc:
                self.error = exc
        return self._f.tell() if size is None else size

    def flush(self) -> None:  # noqa: D102
        pass

    def close(self) -> None:  # noqa: D102
        self._f.close()
        self._kept.clear()
        super().close()


class H5Output:
    """An HDF5 file open for writing whose failure on a full disk is a clean error.

    HDF5 writes through a :class:`_WriteGuard`, so a full disk never leaves the HDF5
    library in a state that crashes the process; :meth:`check` (after a flush) and
    :meth:`close` raise :class:`OutputWriteError` once a write failed, and the file is
    then damaged: remove it.

    Args:
        path: the file.
        mode: ``"w"`` (create or truncate) or ``"a"`` (open an existing file read/write).
        name: the path named in messages [default: ``path``] (e.g. the final name of a
            temporary file).

    Raises:
        OutputWriteError: the file cannot be created or opened for writing (read-only
            folder, full disk).
        OSError: an existing file (``mode="a"``) that is not readable HDF5.
    """

    def __init__(self, path: str | Path, mode: str = "w", name: str | Path | None = None):
        import h5py

        if mode not in ("w", "a"):
            raise ValueError(f"mode must be 'w' or 'a', got {mode!r}")
        self.path = Path(path)
        self.name = self.path if name is None else Path(name)
        with output_errors(self.name, self.path):
            self._io = _WriteGuard(self.path, "w+" if mode == "w" else "r+")
        try:
            self.file = h5py.File(self._io, "w" if mode == "w" else "r+")
        except BaseException:
            self._io.close()
            raise

    def check(self) -> None:
        """Raise if a write failed so far (flush the file first to have written it all).

        Raises:
            OutputWriteError: a write failed (the file is damaged).
        """
        exc = self._io.error
        if exc is not None:
            err = OSError(exc.errno, exc.strerror, os.fspath(self.name))
            msg = filesystem_message(err) or f"cannot write {self.name}: {exc}"
            raise OutputWriteError(msg, exc.errno, self.name) from exc

    def flush(self) -> None:
        """Write everything HDF5 holds to the file, then :meth:`check`."""
        self.file.flush()
        self.check()

    def close(self) -> None:
        """Close the file, then :meth:`check` (a failed write raises even here)."""
        if not self._io.closed:
            try:
                self.file.close()
            finally:
                self._io.close()
        self.check()

    def abandon(self) -> None:
        """Close the file after an error, raising nothing (the file may be incomplete)."""
        with contextlib.suppress(Exception):
            self.close()


@contextlib.contextmanager
def atomic_h5(path: str | Path) -> Iterator[Any]:
    """An ``h5py.File`` written at a temporary name and moved onto ``path`` on success.

    As :func:`atomic_path`, and a full disk at any point (even while HDF5 closes the file)
    raises :class:`OutputWriteError` naming ``path`` instead of crashing the process.
    """
    with atomic_path(path) as tmp:
        out = H5Output(tmp, "w", name=path)
        try:
            yield out.file
        except BaseException:
            out.abandon()
            raise
        out.close()
