"""The base class of every error that a user can fix.

Library code raises a subclass of :class:`FreiPoseError` for bad input (a malformed file,
a wrong option value, a missing camera) with a message that says what was expected, what
was found and how to fix it. The command line shows exactly these errors as one message
without a traceback; any other exception is a bug and keeps its traceback.
"""

from __future__ import annotations

import errno
import os
import shutil


class FreiPoseError(ValueError):
    """An error in the user's input or files, with a message that names the fix.

    It derives from ``ValueError`` so that callers that catch ``ValueError`` for bad
    values keep working.
    """


class InputFileError(FreiPoseError, FileNotFoundError):
    """A file or folder that the user named does not exist or cannot be read."""


class OutputWriteError(FreiPoseError, OSError):
    """An output that cannot be written: its disk is full, or its folder is read-only.

    It is an ``OSError`` too (with the ``errno`` of the cause), so callers that catch
    ``OSError`` for file problems keep working.

    Args:
        message: what cannot be written, why, and what to do.
        code: the ``errno`` of the cause (``ENOSPC``, ``EROFS``...), when known.
        path: the output that cannot be written, when known.
    """

    def __init__(
        self, message: str, code: int | None = None, path: str | os.PathLike[str] | None = None
    ) -> None:
        super().__init__(message)
        self.errno = code
        self.path = path


#: errno values that the user fixes outside FreiPose (free space, choose a writable folder)
DISK_FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})
NOT_WRITABLE_ERRNOS = frozenset({errno.EROFS, errno.EACCES, errno.EPERM})


def filesystem_message(
    exc: OSError,
    path: str | os.PathLike[str] | None = None,
    then: str = "run the command again",
) -> str | None:
    """The message for a full disk, a read-only folder or a denied access, else None.

    Args:
        exc: the error of a file operation.
        path: the file it was about when ``exc`` does not name one (``exc.filename`` wins).
        then: what the user does once the cause is removed.

    Returns:
        One line that names the path, what is wrong and what to do, or None when ``exc`` is
        another kind of error (a bug or an input problem that keeps its own message).
    """
    name = exc.filename if exc.filename is not None else path
    where = f"{os.fsdecode(name)}" if name is not None else "an output file"
    folder = os.path.dirname(os.path.abspath(where)) if name is not None else "its folder"
    if exc.errno in DISK_FULL_ERRNOS:
        what = (
            f"your disk quota on the filesystem holding {folder} is used up"
            if exc.errno == errno.EDQUOT
            else f"the disk holding {folder} is full{_free_text(folder)}"
        )
        return (
            f"cannot write {where}: {what}; free space there (or write to another folder) "
            f"and {then}"
        )
    if exc.errno == errno.EROFS:
        return (
            f"cannot write {where}: {folder} is on a read-only filesystem; choose an output "
            f"in a folder you can write to and {then}"
        )
    if exc.errno in NOT_WRITABLE_ERRNOS:
        return (
            f"{where}: permission denied; give yourself access to it (or choose another "
            f"path) and {then}"
        )
    return None


def _free_text(folder: str) -> str:
    """`` (N MB free)`` for the filesystem of ``folder``, or ``""`` when it cannot be read."""
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return ""
    return f" ({bytes_text(free)} free)"


def bytes_text(n: int) -> str:
    """``"3.2 MB"``, or ``"45 kB"`` below 0.1 MB: a size for a message."""
    return f"{n / 1e6:.1f} MB" if n >= 100_000 else f"{n // 1000} kB"
