"""Join the shard files of ``freipose predict --shard I/N`` into the file a single run gives.

Shard files are named ``<session>.shard-I-of-N.poses.h5``. All N must be present and
complete and come from the same run (same ``run_key``: model, calibration, frame range);
their rows are concatenated in shard order and the shard attributes dropped, so the result
equals, dataset by dataset and attribute by attribute, an unsharded run's output.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Sequence
from pathlib import Path

import h5py
import numpy as np

from freipose.errors import FreiPoseError, InputFileError
from freipose.io.atomic import atomic_h5, refuse_existing, remove_leftover_partials
from freipose.io.calibration_toml import rig_from_toml_text
from freipose.io.calibration_world import resolve_up
from freipose.io.lock import output_lock
from freipose.io.poses import PosesFormatError

log = logging.getLogger(__name__)

SHARD_RE = re.compile(r"^(?P<session>.+)\.shard-(?P<i>\d+)-of-(?P<n>\d+)\.poses\.h5$")
_SHARD_ATTRS = ("shard", "run_range")


class MergeError(FreiPoseError):
    """Shard files cannot be merged; the message says which and why."""


def find_shards(inputs: Sequence[str | Path]) -> dict[str, list[Path]]:
    """Shard files among ``inputs`` (files or folders), grouped by session name.

    Raises:
        MergeError: an input file is not named like a shard file, or nothing was found.
    """
    groups: dict[str, list[Path]] = {}
    for p in map(Path, inputs):
        if p.is_dir():
            files = sorted(f for f in p.iterdir() if SHARD_RE.match(f.name))
        elif p.is_file():
            if not SHARD_RE.match(p.name):
                raise MergeError(
                    f"{p}: not a shard file; shard files are named <session>.shard-I-of-N.poses.h5"
                )
            files = [p]
        else:
            raise InputFileError(f"{p}: no such shard file or folder")
        for f in files:
            m = SHARD_RE.match(f.name)
            assert m is not None
            groups.setdefault(m.group("session"), [])
            if f not in groups[m.group("session")]:
                groups[m.group("session")].append(f)
    if not groups:
        raise MergeError(
            f"no shard files (<session>.shard-I-of-N.poses.h5) in {list(map(str, inputs))}"
        )
    return groups


def _shard_info(path: Path, f: h5py.File) -> tuple[int, int]:
    s = str(f.attrs.get("shard", ""))
    m = re.fullmatch(r"(\d+)/(\d+)", s)
    if not m:
        raise MergeError(f"{path}: no 'shard' attribute; it is not a shard of a sharded run")
    return int(m.group(1)), int(m.group(2))


def merge_shards(shards: Sequence[str | Path], output: str | Path) -> Path:
    """Merge the N shard files of one run into ``output``.

    Raises:
        MergeError: a shard is missing, duplicated, incomplete, or from another run.
        PosesFormatError: a file is not a readable poses file.
    """
    paths = [Path(p) for p in shards]
    infos = []
    for p in paths:
        try:
            f = h5py.File(p, "r")
        except OSError as exc:
            raise PosesFormatError(f"{p}: not a readable HDF5 file ({exc})") from exc
        with f:
            i, n = _shard_info(p, f)
            if not bool(f.attrs.get("complete", False)):
                raise MergeError(f"{p}: shard {i}/{n} is not complete; rerun that shard first")
            infos.append((i, n, str(f.attrs.get("run_key", "")), p, tuple(f.attrs["run_range"])))
    counts = {n for _, n, *_ in infos}
    if len(counts) != 1:
        raise MergeError(
            f"shards of different runs (shard counts {sorted(counts)}): {list(map(str, paths))}"
        )
    n = counts.pop()
    keys = {k for _, _, k, *_ in infos}
    if len(keys) != 1:
        raise MergeError(
            "the shards come from runs with different settings (model, calibration or frame "
            f"range): {list(map(str, paths))}; rerun the odd ones with the same command"
        )
    by_index: dict[int, Path] = {}
    for i, _, _, p, _ in infos:
        if i in by_index:
            raise MergeError(f"shard {i}/{n} given twice: {by_index[i]} and {p}")
        by_index[i] = p
    absent = [i for i in range(n) if i not in by_index]
    if absent:
        raise MergeError(
            f"missing shards {absent} of {n} (have {sorted(by_index)}); run "
            + ", ".join(f"--shard {i}/{n}" for i in absent)
            + " first"
        )
    ordered = [by_index[i] for i in range(n)]
    run_range = infos[0][4]
    files = [h5py.File(p, "r") for p in ordered]
    try:
        fi = np.concatenate([f["frame_index"][()] for f in files])
        want = np.arange(int(run_range[0]), int(run_range[1]), dtype=np.int64)
        if not np.array_equal(fi, want):
            raise MergeError(
                f"the shards' frames do not cover the run's frames {run_range[0]}:{run_range[1]} "
                "exactly once"
            )
        with atomic_h5(output) as out:
            _write_merged(files, out)
    finally:
        for f in files:
            f.close()
    log.info("merged %d shards into %s", n, output)
    return Path(output)


def _write_merged(files: list[h5py.File], out: h5py.File) -> None:
    first = files[0]
    for k, v in first.attrs.items():
        if k not in _SHARD_ATTRS:
            out.attrs[k] = v
    T = sum(f["poses"].shape[0] for f in files)
    chunk_rows = max(f["poses"].chunks[0] for f in files if f["poses"].chunks)

    def copy(name: str) -> None:
        # the layout of a non-empty shard's dataset (an empty shard's is not chunked)
        d0 = next((f[name] for f in files if f[name].chunks is not None), first[name])
        data = np.concatenate([f[name][()] for f in files], axis=0)
        if d0.chunks is None:
            out.create_dataset(name, data=data)
        else:
            out.create_dataset(
                name,
                data=data,
                chunks=(max(1, min(chunk_rows, T)), *d0.shape[1:]),
                fillvalue=d0.fillvalue,
                compression=d0.compression,
                compression_opts=d0.compression_opts,
            )
        for k, v in d0.attrs.items():
            out[name].attrs[k] = v

    names: list[str] = []
    first.visit(names.append)
    for name in names:
        obj = first[name]
        if isinstance(obj, h5py.Group):
            g = out.require_group(name)
            for k, v in obj.attrs.items():
                g.attrs[k] = v
        elif name in ("keypoints", "individuals"):  # per run, not per frame
            out.create_dataset(name, data=obj[()], dtype=obj.dtype)
        else:
            copy(name)
    if "up_source" in first.attrs:
        _estimate_up_again(out)
    out.attrs["completed_frames"] = T
    out.attrs["complete"] = True


def _estimate_up_again(out: h5py.File) -> None:
    """The up of the joined poses, as an unsharded run estimates it from all its frames.

    Shards of a calibration without an up store none of their own (world z, flagged as
    unknown); the joined frames give it when they determine it (see :func:`resolve_up`).
    """
    rig = rig_from_toml_text(str(out.attrs["calibration"]))
    found = resolve_up(rig, out["poses"][()], "the poses' up attribute", what="predicted")
    out.attrs["up"] = found.up
    out.attrs["up_source"] = found.source


def merge_outputs(
    inputs: Sequence[str | Path],
    outdir: str | Path | None = None,
    remove: bool = False,
    overwrite: bool = False,
) -> list[Path]:
    """Merge every session's shards found in ``inputs`` into ``OUTDIR/<session>.poses.h5``.

    Every merged file is written while holding its output lock (see
    :func:`freipose.io.lock.output_lock`); leftovers of a killed merge into the same file
    are removed first.

    Args:
        inputs: shard files and/or folders holding them.
        outdir: where to write; default the folder of each session's first shard.
        remove: delete the shard files after a successful merge.
        overwrite: replace merged files that exist (default: refuse before merging any).

    Raises:
        OutputExistsError: a merged file exists and ``overwrite`` is false.
        OutputLockedError: another run is writing a merged file.
    """
    jobs = []
    for session, files in sorted(find_shards(inputs).items()):
        folder = Path(outdir) if outdir is not None else files[0].parent
        jobs.append((folder / f"{session}.poses.h5", files))
    for target, _ in jobs:
        refuse_existing(target, overwrite)
    out = []
    for target, files in jobs:
        with output_lock(target, "poses file"):
            refuse_existing(target, overwrite)
            remove_leftover_partials(target)
            merge_shards(files, target)
        if remove:
            for f in files:
                f.unlink()
        out.append(target)
    return out
