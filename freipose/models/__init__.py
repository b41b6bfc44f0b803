"""Pretrained base models shipped with FreiPose (weights and their model card data).

The weights are package data next to this module, listed in ``bases.json``: one entry per
base model with its ``name``, ``kind`` (``voxel``, ``baseline`` or ``detector``), ``file``,
``architecture`` (the ``[model]`` table, or the detector's input size, width and neck),
``skeleton``, ``steps`` and provenance (the command, the data seeds, the held-out
figures). ``benchmarks/train_base.py`` writes both; ``docs/models.md`` describes them. The
files are read from the installed package (``importlib.resources``); nothing is downloaded.
"""

from __future__ import annotations

import json
from collections.abc import Collection, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from importlib import resources
from importlib.resources.abc import Traversable
from pathlib import Path
from typing import Any

MANIFEST = "bases.json"


@dataclass(frozen=True)
class BaseModel:
    """One shipped base model (an entry of ``bases.json``).

    Attributes:
        name: the base's name (``voxel``, ``baseline``, ``detector``).
        kind: the network it initialises (``voxel``, ``baseline`` or ``detector``).
        file: the weights file's name in this package.
        architecture: the settings that fix the weights' shapes (and the rest of the
            ``[model]`` table it was trained with).
        steps: optimizer steps it was trained for, those of the weights it was warm-started
            from included (:func:`total_steps`).
        entry: the whole manifest entry (provenance, held-out figures).
    """

    name: str
    kind: str
    file: str
    architecture: Mapping[str, Any]
    steps: int
    entry: Mapping[str, Any]


def read_manifest(path: Path | Traversable) -> list[dict[str, Any]]:
    """The entries of a ``bases.json`` file (empty when there is no such file).

    Args:
        path: the manifest, on disk or in the installed package.

    Returns:
        Its ``bases`` list.
    """
    if not path.is_file():
        return []
    return list(json.loads(path.read_text(encoding="utf-8")).get("bases", []))


def total_steps(entry: Mapping[str, Any]) -> int:
    """The steps of a manifest entry plus those of the weights it was warm-started from.

    Args:
        entry: a ``bases.json`` entry; its ``started_from`` (if any) holds the total steps
            of the weights its training started from.

    Returns:
        All optimizer steps behind the weights.
    """
    return int(entry["steps"]) + int(entry.get("started_from", {}).get("steps", 0))


def _root() -> Traversable:
    """The folder of the shipped weights: this package's data."""
    return resources.files(__name__)


def shipped_bases() -> tuple[BaseModel, ...]:
    """The base models in the installed package whose weights file is present."""
    root = _root()
    out = []
    for e in read_manifest(root / MANIFEST):
        if (root / e["file"]).is_file():
            arch, steps = e["architecture"], total_steps(e)
            out.append(BaseModel(e["name"], e["kind"], e["file"], arch, steps, e))
    return tuple(out)


def find_base(
    kind: str, architecture: Mapping[str, Any], keys: Collection[str]
) -> BaseModel | None:
    """The shipped base of ``kind`` whose ``keys`` of the architecture equal ``architecture``'s.

    Args:
        kind: ``voxel``, ``baseline`` or ``detector``.
        architecture: the run's settings (lists and tuples compare equal).
        keys: the settings that must agree (those that fix the weights' shapes).

    Returns:
        The base, or None when none is shipped for this architecture.
    """

    def norm(v: Any) -> Any:
        return list(v) if isinstance(v, (list, tuple)) else v

    for base in shipped_bases():
        if base.kind == kind and all(
            norm(base.architecture.get(k)) == norm(architecture.get(k)) for k in keys
        ):
            return base
    return None


@contextmanager
def base_file(base: BaseModel) -> Iterator[Path]:
    """The weights file of ``base`` as a path on disk, within the block."""
    with resources.as_file(_root() / base.file) as path:
        yield Path(path)
