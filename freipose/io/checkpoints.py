"""The kinds of FreiPose checkpoint files, read safely, and the check that a file is the right one.

Every checkpoint that FreiPose writes is a ``torch.save`` dict whose ``format`` and
``kind`` entries say what it is (see docs/formats.md):

* ``"pose"``: a pose network (``model.pt``, ``checkpoint.pt`` of ``freipose train``);
  format ``freipose.pose_checkpoint``, kind ``voxel``;
* ``"baseline"``: the triangulation baseline (``freipose train --stage baseline``); format
  ``freipose.pose_checkpoint``, kind ``baseline``;
* ``"detector"``: a trained detector (``detector.pt`` of ``freipose train --stage
  detector``); format ``freipose.detector``, kind ``detector``;
* ``"detector_training_state"``: a detector with its optimizer state (``detector_last.pt``,
  what ``--resume`` continues); format ``freipose.detector``, kind
  ``detector_training_state``.

Detector files written before they had a ``kind`` are told apart by their ``optimizer``
entry. Anything else is ``"other"``: not a FreiPose checkpoint (or written by another
program).

Files are read with ``torch.load(..., weights_only=True)``, which builds only tensors,
plain containers and (allowed here) NumPy arrays, so reading a file never runs code from
it. A file that needs anything else is of kind ``"other"``.
"""

from __future__ import annotations

import contextlib
import pickle
import warnings
import zipfile
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any

from freipose.errors import FreiPoseError, InputFileError

POSE_FORMAT = "freipose.pose_checkpoint"
DETECTOR_FORMAT = "freipose.detector"

#: kind -> how a message names a file of that kind
KIND_NAMES: Mapping[str, str] = MappingProxyType(
    {
        "pose": "a pose-network checkpoint",
        "baseline": "a pose-network checkpoint (the triangulation baseline)",
        "detector": "a detector checkpoint",
        "detector_training_state": "a detector training checkpoint (detector_last.pt)",
        "other": "not a FreiPose checkpoint (or written by another program)",
    }
)


class CheckpointFileError(FreiPoseError):
    """A checkpoint file that cannot be read, or a checkpoint of another kind than asked for."""


@dataclass(frozen=True)
class CheckpointUse:
    """What a loader accepts: the kinds, how to name them, and the command that writes them.

    Attributes:
        kinds: the accepted kinds (keys of :data:`KIND_NAMES`).
        wanted: the accepted files as a message names them.
        command: the command that writes such a file.
    """

    kinds: frozenset[str]
    wanted: str
    command: str


POSE_NETWORK = CheckpointUse(
    frozenset({"pose", "baseline"}), "a pose-network checkpoint", "freipose train CONFIG"
)
DETECTOR = CheckpointUse(
    frozenset({"detector", "detector_training_state"}),
    "a detector checkpoint",
    "freipose train CONFIG --stage detector",
)
DETECTOR_TRAINING_STATE = CheckpointUse(
    frozenset({"detector_training_state"}),
    "a detector training checkpoint (detector_last.pt)",
    "freipose train CONFIG --stage detector",
)


def _numpy_globals() -> list[Any]:
    """The NumPy names a checkpoint's random-generator state needs (arrays and dtypes).

    Each is allowed under the name NumPy 2 writes and the one NumPy 1 writes.
    """
    import numpy as np

    try:
        from numpy._core import multiarray
    except ImportError:  # NumPy 1
        from numpy.core import multiarray  # type: ignore[no-redef]
    out: list[Any] = [np.ndarray, np.dtype]
    for name in ("_reconstruct", "scalar"):
        fn = getattr(multiarray, name)
        out += [(fn, f"numpy._core.multiarray.{name}"), (fn, f"numpy.core.multiarray.{name}")]
    dtypes = getattr(np, "dtypes", None)
    if dtypes is not None:
        out += [getattr(dtypes, n) for n in dtypes.__all__]
    return out


@contextlib.contextmanager
def _numpy_allowed() -> Iterator[None]:
    """Allow :func:`_numpy_globals` in ``torch.load(weights_only=True)`` within the block."""
    import torch

    safe = getattr(torch.serialization, "safe_globals", None)
    if safe is None:  # torch before 2.5: allowed for the rest of the process
        torch.serialization.add_safe_globals(_numpy_globals())
        yield
        return
    with safe(_numpy_globals()):
        yield


class _Unsafe:
    """The marker :func:`load_safely` returns for a file it does not build."""

    def __repr__(self) -> str:
        return "UNSAFE"


#: what :func:`load_safely` returns for a file that is not only tensors, containers, arrays
UNSAFE: Any = _Unsafe()


def _damaged(path: Path, detail: str, error: type[CheckpointFileError]) -> CheckpointFileError:
    """The error for a file that looks like a checkpoint but cannot be read to its end."""
    return error(f"{path}: not a readable checkpoint ({detail}); is it truncated?")


def load_safely(
    path: str | Path, mmap: bool = False, error: type[CheckpointFileError] = CheckpointFileError
) -> Any:
    """Read a ``torch.save`` file without running code from it (tensors on the CPU).

    Args:
        path: the file.
        mmap: map the tensors' storage instead of reading it (zip-format files only).
        error: the class of the error raised for a damaged file.

    Returns:
        The stored object; :data:`UNSAFE` when the file needs more than tensors, plain
        containers and NumPy arrays (not written by FreiPose).

    Raises:
        InputFileError: no such file.
        CheckpointFileError: an empty file or a damaged (e.g. truncated) ``torch.save`` file.
    """
    import torch

    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"checkpoint not found: {path}")
    if path.stat().st_size == 0:
        raise _damaged(path, "the file is empty", error)
    is_zip = zipfile.is_zipfile(path)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*weights_only")
            with _numpy_allowed():
                return torch.load(path, map_location="cpu", weights_only=True, mmap=mmap and is_zip)
    except pickle.UnpicklingError:
        return UNSAFE
    except Exception as exc:  # noqa: BLE001 - torch raises many kinds for damaged files
        if "weights_only" not in str(exc) and (is_zip or _starts_like_torch_zip(path)):
            raise _damaged(path, str(exc).split(". ")[0], error) from exc
        return UNSAFE


def _starts_like_torch_zip(path: Path) -> bool:
    """Whether the file starts like a zip archive (what ``torch.save`` writes)."""
    with path.open("rb") as f:
        return f.read(4) == b"PK\x03\x04"


def kind_of(obj: Any) -> str:
    """The kind of a loaded checkpoint (see the module docstring)."""
    if not isinstance(obj, Mapping):
        return "other"
    fmt = obj.get("format")
    if fmt == POSE_FORMAT:
        kind = obj.get("kind")
        if kind is None and isinstance(obj.get("config"), Mapping):
            kind = obj["config"].get("model", {}).get("kind")
        return "baseline" if kind == "baseline" else "pose"
    if fmt == DETECTOR_FORMAT:
        kind = obj.get("kind")
        if kind in ("detector", "detector_training_state"):
            return str(kind)
        return "detector_training_state" if "optimizer" in obj else "detector"
    return "other"


def checkpoint_kind(path: str | Path) -> str:
    """The kind of a checkpoint file: a key of :data:`KIND_NAMES`.

    Args:
        path: the file.

    Returns:
        ``"pose"``, ``"baseline"``, ``"detector"``, ``"detector_training_state"`` or
        ``"other"``.

    Raises:
        InputFileError: no such file.
        CheckpointFileError: an empty or damaged (e.g. truncated) checkpoint.
    """
    return kind_of(load_safely(path, mmap=True))


def kind_error(
    path: str | Path,
    kind: str,
    use: CheckpointUse,
    option: str | None = None,
    error: type[CheckpointFileError] = CheckpointFileError,
) -> CheckpointFileError:
    """The error for a file of ``kind`` given where ``use`` is needed.

    Args:
        path: the file.
        kind: its kind.
        use: what was needed.
        option: the option (or argument) that named the file; None: say what was expected.
        error: the class of the error.

    Returns:
        The error, e.g. "FILE is a pose-network checkpoint; --detector takes a detector
        checkpoint (`freipose train CONFIG --stage detector`)".
    """
    takes = f"{option} takes" if option else "expected"
    return error(f"{path} is {KIND_NAMES[kind]}; {takes} {use.wanted} (`{use.command}`)")


def read_checkpoint_as(
    path: str | Path,
    use: CheckpointUse,
    option: str | None = None,
    error: type[CheckpointFileError] = CheckpointFileError,
) -> dict[str, Any]:
    """Read a checkpoint file safely and check that it is of a kind ``use`` accepts.

    Args:
        path: the file.
        use: the accepted kinds.
        option: the option (or argument) that named the file, for the message.
        error: the class of the error raised for a damaged file or one of another kind.

    Returns:
        The checkpoint dict (tensors on the CPU).

    Raises:
        InputFileError: no such file.
        CheckpointFileError: a damaged file or one of another kind (see :func:`kind_error`).
    """
    obj = load_safely(path, error=error)
    kind = kind_of(obj)
    if kind not in use.kinds:
        raise kind_error(path, kind, use, option, error)
    return dict(obj)


def check_checkpoints(*given: tuple[str, str | Path | None, CheckpointUse]) -> None:
    """Check the kinds of the checkpoints that a command's options name, before any work.

    Args:
        given: ``(option, path or None, use)`` per option; None paths are skipped.

    Raises:
        InputFileError: no such file.
        CheckpointFileError: a damaged file or one of another kind.
    """
    for option, path, use in given:
        if path is None:
            continue
        kind = checkpoint_kind(path)
        if kind not in use.kinds:
            raise kind_error(path, kind, use, option)


__all__ = [
    "DETECTOR",
    "DETECTOR_FORMAT",
    "DETECTOR_TRAINING_STATE",
    "KIND_NAMES",
    "POSE_FORMAT",
    "POSE_NETWORK",
    "UNSAFE",
    "CheckpointFileError",
    "CheckpointUse",
    "check_checkpoints",
    "checkpoint_kind",
    "kind_error",
    "kind_of",
    "load_safely",
    "read_checkpoint_as",
]
