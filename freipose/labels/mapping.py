"""Renaming keypoints and cameras on import: ``--map old=new`` options and mapping files.

A mapping file is TOML (documented in ``docs/formats.md``)::

    [keypoints]          # source name = FreiPose name; "" drops the keypoint
    snout = "Nose"
    leftear = "Ear Left"
    tailtip = ""

    [cameras]            # source camera (folder, file or camera name) = calibration camera
    "run1-camA" = "cam0"
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType

from freipose._frozen import PicklableFrozen
from freipose.errors import FreiPoseError
from freipose.io.toml import did_you_mean, read_toml

log = logging.getLogger(__name__)


class MappingError(FreiPoseError):
    """A mapping option or file is malformed, or names do not fit the skeleton."""


@dataclass(frozen=True, eq=False)
class NameMapping(PicklableFrozen):
    """Renames applied to source keypoint and camera names ("" as a target drops the name)."""

    keypoints: Mapping[str, str] = field(default_factory=dict)
    cameras: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        """Freeze the tables."""
        object.__setattr__(self, "keypoints", MappingProxyType(dict(self.keypoints)))
        object.__setattr__(self, "cameras", MappingProxyType(dict(self.cameras)))

    def merged(self, other: NameMapping) -> NameMapping:
        """This mapping updated by ``other`` (``other`` wins on conflicts).

        Args:
            other: the mapping whose entries win.

        Returns:
            The merged mapping.
        """
        return NameMapping({**self.keypoints, **other.keypoints}, {**self.cameras, **other.cameras})

    def keypoint(self, name: str) -> str:
        """The new name of source keypoint ``name`` (itself when not mapped; "" drops it)."""
        return self.keypoints.get(name, name)

    def camera(self, name: str) -> str:
        """The new name of source camera ``name`` (itself when not mapped)."""
        return self.cameras.get(name, name)


def parse_map_options(items: Iterable[str], what: str = "--map") -> dict[str, str]:
    """Parse ``--map`` options: ``["old=new", ...]`` -> ``{old: new}``; ``old=`` drops ``old``.

    Args:
        items: the option values.
        what: the option's name, for messages.

    Returns:
        Old name -> new name.

    Raises:
        MappingError: an item without ``=`` or with an empty old name.
    """
    out: dict[str, str] = {}
    for item in items:
        if "=" not in item:
            raise MappingError(f"{what} {item!r}: expected OLD=NEW (e.g. {what} snout=Nose)")
        old, new = item.split("=", 1)
        old, new = old.strip(), new.strip()
        if not old:
            raise MappingError(f"{what} {item!r}: the old name is empty")
        out[old] = new
    return out


def load_mapping_file(path: str | Path) -> NameMapping:
    """Read a TOML mapping file (``[keypoints]`` and ``[cameras]`` tables of strings).

    Args:
        path: the mapping file.

    Returns:
        The mapping.

    Raises:
        InputFileError: no such file.
        MappingError: not TOML, unknown tables, or values that are not strings.
    """
    path = Path(path)
    data = read_toml(path, "mapping file", MappingError)
    unknown = sorted(set(data) - {"keypoints", "cameras"})
    if unknown:
        hint = did_you_mean(unknown[0], ("keypoints", "cameras"))
        raise MappingError(
            f"{path}: unknown tables {unknown}{hint} (a mapping file has [keypoints] and "
            f"[cameras] tables of 'source name = \"new name\"' entries)"
        )
    tables = {}
    for key in ("keypoints", "cameras"):
        t = data.get(key, {})
        bad = {k: v for k, v in t.items() if not isinstance(v, str)} if isinstance(t, dict) else t
        if not isinstance(t, dict) or bad:
            raise MappingError(f"{path}: [{key}] values must be strings (new names), got {bad}")
        tables[key] = dict(t)
    return NameMapping(tables["keypoints"], tables["cameras"])


def resolve_keypoints(
    source_names: Sequence[str],
    mapping: NameMapping,
    skeleton_keypoints: Sequence[str] | None,
    source: str,
    ignore_unknown: bool = False,
) -> tuple[tuple[str, ...], list[int | None]]:
    """Map source keypoint names onto the target keypoint list.

    Returns:
        ``(target_keypoints, index)`` where ``index[i]`` is the target index of source
        keypoint ``i`` (None where it is dropped).

    Raises:
        MappingError: source keypoints (after renaming) that the skeleton lacks, naming them
            (unless ``ignore_unknown``), two source keypoints mapped to one name, or no
            keypoint in common at all.
    """
    renamed = [mapping.keypoint(n) for n in source_names]
    unused = sorted(set(mapping.keypoints) - set(source_names))
    if unused:
        log.warning("%s: --map names %s that the source does not have", source, unused)
    kept = [n for n in renamed if n]
    dup = sorted({n for n in kept if kept.count(n) > 1})
    if dup:
        raise MappingError(f"{source}: several source keypoints map to {dup}; map them apart")
    if skeleton_keypoints is None:
        target = tuple(kept)
    else:
        target = tuple(skeleton_keypoints)
        unknown = [
            f"{s!r}" + (f" (mapped to {r!r})" if r != s else "")
            for s, r in zip(source_names, renamed)
            if r and r not in target
        ]
        if len(unknown) == len(kept) or not kept:
            raise MappingError(
                f"{source}: none of the source keypoints {list(source_names)} is in the "
                f"skeleton {list(target)}; map them with --map SOURCE=SKELETON or a mapping file"
            )
        if unknown and not ignore_unknown:
            raise MappingError(
                f"{source}: keypoints {', '.join(unknown)} are not in the skeleton "
                f"{list(target)}; rename them with --map SOURCE=SKELETON, drop them with "
                f"--map SOURCE=, or pass --ignore-unknown"
            )
        if unknown:
            log.warning(
                "%s: dropping keypoints not in the skeleton: %s", source, ", ".join(unknown)
            )
        missing = [k for k in target if k not in renamed]
        if missing:
            log.warning("%s: the source has no labels for skeleton keypoints %s", source, missing)
    index: list[int | None] = [target.index(r) if r and r in target else None for r in renamed]
    return target, index
