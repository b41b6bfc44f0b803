"""The base class of every error that a user can fix.

Library code raises a subclass of :class:`FreiPoseError` for bad input (a malformed file,
a wrong option value, a missing camera) with a message that says what was expected, what
was found and how to fix it. The command line shows exactly these errors as one message
without a traceback; any other exception is a bug and keeps its traceback.
"""

from __future__ import annotations


class FreiPoseError(ValueError):
    """An error in the user's input or files, with a message that names the fix.

    It derives from ``ValueError`` so that callers that catch ``ValueError`` for bad
    values keep working.
    """


class InputFileError(FreiPoseError, FileNotFoundError):
    """A file or folder that the user named does not exist or cannot be read."""
