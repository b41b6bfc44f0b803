"""Incremental, resumable writer of ``poses.h5`` (the schema of ``freipose.io.poses``).

The output is written to ``<name>.poses.h5.partial``: all datasets are created at their
full size up front (NaN / confidence 0 / status -1), and predictions are written one chunk
of rows at a time; after each chunk the attribute ``completed_frames`` records how many
leading rows are final. A killed run restarted with the same settings reopens the partial
file and continues after ``completed_frames``; when all rows are written the attribute
``complete`` is set to true and the file is renamed to ``<name>.poses.h5``.

Several animals: a header with ``individuals`` gives the file an animal axis (the layout of
``freipose.io.poses``: ``poses`` (T, A, K, 3), the per-animal extras (T, A, ...), the
``individuals`` and ``identity_confidence`` (T, A) datasets); rows are added with
:meth:`IncrementalPosesWriter.add_animals`, one :class:`Estimate` per animal.

A partial file written with different settings (another model, calibration, frame range
or shard) is discarded with a warning, as is one that is damaged (killed while HDF5 was
writing its metadata, or written until the disk was full): before resuming, the chunk index
of every dataset is checked against the file's size and the last committed rows are read
back. ``open(fresh=True)`` never resumes.

The file is written through :class:`~freipose.io.atomic.H5Output`: a disk that fills up
during the run ends it with :class:`~freipose.errors.OutputWriteError` (the damaged
partial file is removed), and the run refuses to start when the disk has less free space
than the output can take.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator, Sequence
from pathlib import Path

import h5py
import numpy as np

from freipose.errors import OutputWriteError
from freipose.io.atomic import H5Output, output_errors
from freipose.io.calibration_world import WorldUp
from freipose.predict.estimator import Estimate
from freipose.predict.writer_layout import (
    STATUS_FEW_VIEWS,
    STATUS_NOT_FOUND,
    STATUS_OK,
    OutputHeader,
    check_free_space,
    create_layout,
    output_bytes,
)

log = logging.getLogger(__name__)

PARTIAL_SUFFIX = ".partial"

#: the status codes and the header, where the writer's users look for them
__all__ = ["STATUS_FEW_VIEWS", "STATUS_NOT_FOUND", "STATUS_OK", "IncrementalPosesWriter",
           "OutputHeader", "is_complete", "partial_path"]  # fmt: skip


def partial_path(path: str | Path) -> Path:
    """Where the unfinished output of ``path`` is written."""
    path = Path(path)
    return path.with_name(path.name + PARTIAL_SUFFIX)


def is_complete(path: str | Path) -> bool:
    """True if ``path`` is a poses file whose ``complete`` attribute is set."""
    path = Path(path)
    if not path.is_file():
        return False
    try:
        with h5py.File(path, "r") as f:
            return bool(f.attrs.get("complete", False))
    except OSError:
        return False


def verify_partial(f: h5py.File, size: int) -> None:
    """Raise if the partial file ``f`` (of ``size`` bytes) is damaged.

    Every chunk of every dataset must lie inside the file, and the last committed rows
    must read back.

    Raises:
        OSError, RuntimeError, ValueError, KeyError: the file is damaged.
    """
    done = int(f.attrs["completed_frames"])
    for name in _PATHS.values():
        if name not in f and name in _ANIMAL_ONLY:  # one animal: no such dataset
            continue
        d = f[name]
        if d.chunks is not None:
            for i in range(d.id.get_num_chunks()):
                info = d.id.get_chunk_info(i)
                if info.byte_offset is None or info.byte_offset + info.size > size:
                    raise ValueError(f"{name}: chunk {i} lies beyond the end of the file")
        if done:
            d[max(0, done - 1) : done]
    for name in ("keypoints", "frame_index"):
        f[name][()]


ROW_FIELDS = (
    "poses",
    "confidence",
    "points2d",
    "confidence2d",
    "boxes",
    "center",
    "uncertainty",
    "status",
    "frame_ok",
)
_ANIMAL_ONLY = ("identity_confidence", "extra/identity_flagged")
ANIMAL_ROW_FIELDS = (*ROW_FIELDS, "identity_confidence", "identity_flagged")  # an animal axis
_ANIMAL_FIELDS = tuple(k for k in ANIMAL_ROW_FIELDS if k not in ("status", "frame_ok"))
ORDER_PATH = "extra/identity_order"  #: (T, A) int8, the track each animal's row came from
_PATHS = {
    "poses": "poses",
    "confidence": "confidence",
    "identity_confidence": "identity_confidence",
    "identity_flagged": "extra/identity_flagged",
    **{n: f"extra/{n}" for n in ROW_FIELDS[2:]},
}


def _rows(est: Estimate) -> dict[str, np.ndarray]:
    """The per-row arrays of one animal's estimate, by field name."""
    return {
        "poses": est.poses,
        "confidence": est.confidence,
        "points2d": est.points2d,
        "confidence2d": est.confidence2d,
        "boxes": est.boxes,
        "center": est.center,
        "uncertainty": (
            np.full(est.confidence.shape, np.nan, np.float32)
            if est.uncertainty is None
            else est.uncertainty
        ),
    }


class IncrementalPosesWriter:
    """Write the rows of one output file in order, resumably.

    Args:
        path: final path (``.../<name>.poses.h5``); work happens in ``path + ".partial"``.
        header: the file's settings.
        chunk_rows: rows per HDF5 chunk and per commit (a kill loses at most this many).

    Usage::

        w = IncrementalPosesWriter(path, header, 256)
        done = w.open()            # rows already final (resume point)
        w.add(estimate, status, frame_ok)   # rows done, done+1, ... in order
        w.finish()                 # -> path
    """

    def __init__(self, path: str | Path, header: OutputHeader, chunk_rows: int = 256):
        if chunk_rows < 1:
            raise ValueError(f"chunk_rows must be positive, got {chunk_rows}")
        self.path = Path(path)
        self.partial = partial_path(self.path)
        self.header = header
        self.chunk_rows = int(chunk_rows)
        self._out: H5Output | None = None
        self._fields = ROW_FIELDS if header.individuals is None else ANIMAL_ROW_FIELDS
        self._buf: dict[str, list[np.ndarray]] = {k: [] for k in self._fields}
        self._buffered = 0
        self.completed = 0

    # -- open / resume --------------------------------------------------------------------
    def _try_resume(self) -> H5Output | None:
        if not self.partial.exists():
            return None
        try:
            out = H5Output(self.partial, "a", name=self.path)
        except OutputWriteError:
            raise
        except OSError as exc:
            log.warning("%s cannot be opened (%s); starting this output again", self.partial, exc)
            return None
        f = out.file
        try:
            key = str(f.attrs.get("run_key", ""))
            shard = str(f.attrs.get("shard", ""))
            T = f["poses"].shape[0] if "poses" in f else -1
            if (
                key != self.header.run_key()
                or shard != self.header.shard_text()
                or self.header.num_frames != T
            ):
                log.warning(
                    "%s was written with other settings (model, calibration, frames or shard); "
                    "starting this output again",
                    self.partial,
                )
                out.abandon()
                return None
            verify_partial(f, self.partial.stat().st_size)
        except (OSError, RuntimeError, ValueError, KeyError) as exc:
            log.warning(
                "the partial file %s from an interrupted run is damaged (%s); starting this "
                "output again",
                self.partial,
                str(exc).splitlines()[0] if str(exc) else type(exc).__name__,
            )
            out.abandon()
            return None
        return out

    def open(self, fresh: bool = False) -> int:
        """Open (resume or create) the partial file; returns the number of final rows.

        Args:
            fresh: start again even when a partial file of the same run could be resumed.

        Raises:
            OutputWriteError: the output folder cannot be written, or the disk holding it
                has less free space than the output can take.
        """
        with output_errors(self.path):
            self.path.parent.mkdir(parents=True, exist_ok=True)
        out = None if fresh else self._try_resume()
        if out is not None:
            self.completed = int(out.file.attrs.get("completed_frames", 0))
            if self.completed:
                log.info(
                    "%s: resuming after %d of %d frames",
                    self.partial,
                    self.completed,
                    self.header.num_frames,
                )
            self._out = out
            return self.completed
        with output_errors(self.path, self.partial):
            self.partial.unlink(missing_ok=True)
        check_free_space(self.path, output_bytes(self.header))
        out = H5Output(self.partial, "w", name=self.path)
        self._out = out
        try:
            create_layout(out.file, self.header, self.chunk_rows)
            out.flush()
        except BaseException:
            self._give_up()
            raise
        self.completed = 0
        return self.completed

    @property
    def _f(self) -> h5py.File | None:
        """The open HDF5 file, or None."""
        return None if self._out is None else self._out.file

    def _give_up(self) -> None:
        """Close and remove a partial file that a failed write left damaged."""
        if self._out is not None:
            self._out.abandon()
            self._out = None
        with contextlib.suppress(OSError):
            self.partial.unlink(missing_ok=True)

    # -- writing --------------------------------------------------------------------------
    def add(self, est: Estimate, status: np.ndarray, frame_ok: np.ndarray) -> None:
        """Append the next ``B`` rows (B = ``est.batch_size``) of a one-animal output."""
        if self.header.individuals is not None:
            raise ValueError("an output with an animal axis takes add_animals(), not add()")
        self._add(est.batch_size, _rows(est), status, frame_ok)

    def add_animals(
        self,
        ests: Sequence[Estimate],
        status: np.ndarray,
        frame_ok: np.ndarray,
        identity_confidence: np.ndarray | None = None,
        flagged: np.ndarray | None = None,
    ) -> None:
        """Append the next ``B`` rows of an output with an animal axis.

        Args:
            ests: (A,) one estimate per animal of the header's ``individuals``, in order,
                each of B rows (an animal not found: NaN poses, confidence 0).
            status: (B,) status per frame.
            frame_ok: (B, C) the frames that were decoded.
            identity_confidence: (B, A) in [0, 1], or None (NaN: unknown).
            flagged: (B, A) bool, an identity swap cannot be ruled out (None: none flagged).

        Raises:
            ValueError: not one estimate per animal, or estimates of different lengths.
        """
        names = self.header.individuals
        if names is None or len(ests) != len(names):
            raise ValueError(
                f"add_animals takes one estimate per animal of {names}, got {len(ests)}"
            )
        B = ests[0].batch_size
        if any(e.batch_size != B for e in ests):
            raise ValueError("the animals' estimates must have the same number of rows")
        per = [_rows(e) for e in ests]
        vals = {k: np.stack([r[k] for r in per], axis=1) for k in per[0]}
        ident = np.full((B, len(names)), np.nan, np.float32)
        if identity_confidence is not None:
            ident = np.asarray(identity_confidence, np.float32).reshape(B, len(names))
        vals["identity_confidence"] = ident
        flags = np.zeros((B, len(names)), bool) if flagged is None else flagged
        vals["identity_flagged"] = np.asarray(flags, bool).reshape(B, len(names))
        self._add(B, vals, status, frame_ok)

    def _add(
        self, B: int, vals: dict[str, np.ndarray], status: np.ndarray, frame_ok: np.ndarray
    ) -> None:
        """Buffer ``B`` rows of ``vals`` and commit the whole chunks."""
        if self._f is None:
            raise RuntimeError("IncrementalPosesWriter.add before open()")
        if self.completed + self._buffered + B > self.header.num_frames:
            raise ValueError(
                f"writing {B} rows after {self.completed + self._buffered} overflows the "
                f"{self.header.num_frames}-frame output"
            )
        vals = {
            **vals,
            "status": np.asarray(status, np.int8).reshape(B),
            "frame_ok": np.asarray(frame_ok, bool).reshape(B, -1),
        }
        for k, v in vals.items():
            self._buf[k].append(v)
        self._buffered += B
        # commit whole chunks (aligned to row 0 of the file)
        while self._buffered:
            boundary = (self.completed // self.chunk_rows + 1) * self.chunk_rows
            boundary = min(boundary, self.header.num_frames)
            if self.completed + self._buffered < boundary:
                break
            self._commit(boundary - self.completed)

    def _commit(self, n: int) -> None:
        """Write the first ``n`` buffered rows; a failed write removes the partial file."""
        assert self._out is not None
        try:
            # a nearly full disk stops the run here, cleanly, whether or not HDF5 would
            # have found room for these rows in space the file already holds
            need = sum(a.nbytes for k in self._fields for a in self._buf[k])
            check_free_space(self.path, need, "its next rows take")
            self._write_rows(self._out, n)
        except OutputWriteError:
            self._give_up()
            raise

    def _write_rows(self, out: H5Output, n: int) -> None:
        a = self.completed
        rest: dict[str, list[np.ndarray]] = {}
        for k in self._fields:
            arr = np.concatenate(self._buf[k], axis=0)
            out.file[_PATHS[k]][a : a + n] = arr[:n]
            rest[k] = [arr[n:]] if len(arr) > n else []
        self._buf = rest
        self._buffered -= n
        out.flush()
        self.completed = a + n
        out.file.attrs["completed_frames"] = self.completed
        out.flush()

    def poses(self) -> np.ndarray:
        """(T, K, 3) the poses committed so far (NaN in rows not yet written); (T, A, K, 3)."""
        if self._f is None:
            raise RuntimeError("IncrementalPosesWriter.poses before open()")
        return self._f["poses"][()]

    def stored_animal_order(self) -> np.ndarray | None:
        """(T, A) the animal order a :meth:`reorder_animals` began with, or None (not begun)."""
        if self._f is None:
            raise RuntimeError("IncrementalPosesWriter.stored_animal_order before open()")
        return self._f[ORDER_PATH][()].astype(np.int64) if ORDER_PATH in self._f else None

    def reorder_animals(self, order: np.ndarray) -> None:
        """Reorder the animal axis of every row, once all rows are written.

        Animal ``a``'s row ``t`` becomes input row ``order[t, a]`` in every per-animal
        dataset, and ``extra/identity_flagged`` is set where an animal's row changes from
        the frame before (where the order moved an animal to another track). The order is
        stored first (``extra/identity_order``, kept in the output: the track each animal's
        pose came from); the rows are then rewritten a chunk at a time, the attribute
        ``reordered_frames`` counting them, so that a run killed here and resumed passes
        :meth:`stored_animal_order` again and finishes the same reordering.

        Args:
            order: (T, A) int, each row a permutation of the animals.

        Raises:
            ValueError: not all rows are written, or ``order`` is not per-frame permutations.
        """
        f = self._f
        if f is None or self.header.individuals is None:
            raise RuntimeError("reorder_animals needs an open output with an animal axis")
        t_n, a_n = self.header.num_frames, len(self.header.individuals)
        order = np.asarray(order, np.int64)
        if self.completed != t_n or self._buffered:
            raise ValueError(f"reorder_animals after {self.completed} of {t_n} rows")
        if order.shape != (t_n, a_n) or not (np.sort(order, 1) == np.arange(a_n)).all():
            raise ValueError(f"order must be (T, A) = ({t_n}, {a_n}) permutations")
        stored = self.stored_animal_order()
        if stored is not None and not np.array_equal(stored, order):
            raise ValueError(f"{self.partial} was being reordered in another order")
        out = self._out
        assert out is not None
        moved = np.zeros((t_n, a_n), bool)
        moved[1:] = order[1:] != order[:-1]
        if stored is None:
            with self._removed_if_failed(out):
                f.create_dataset(ORDER_PATH, data=order.astype(np.int8))
                f.attrs["reordered_frames"] = 0
        for lo in range(int(f.attrs.get("reordered_frames", t_n)), t_n, self.chunk_rows):
            hi = min(lo + self.chunk_rows, t_n)
            if (order[lo:hi] == np.arange(a_n)).all() and not moved[lo:hi].any():
                continue  # nothing moves in these rows
            rows = {k: f[_PATHS[k]][lo:hi] for k in _ANIMAL_FIELDS}
            # rewritten chunks are compressed anew and may take more room than they did; a
            # disk too full for them stops here with the file intact (resumable)
            check_free_space(self.path, sum(v.nbytes for v in rows.values()),
                             "its reordered rows take")  # fmt: skip
            with self._removed_if_failed(out):
                for k, v in rows.items():
                    sel = order[lo:hi].reshape(hi - lo, a_n, *(1,) * (v.ndim - 2))
                    v = np.take_along_axis(v, sel, axis=1)
                    f[_PATHS[k]][lo:hi] = v | moved[lo:hi] if k == "identity_flagged" else v
                f.attrs["reordered_frames"] = hi

    @contextlib.contextmanager
    def _removed_if_failed(self, out: H5Output) -> Iterator[None]:
        """Writes, then a flush; a failed one removes the (then damaged) partial file."""
        try:
            yield
            out.flush()
        except OutputWriteError:
            self._give_up()
            raise

    def finish(self, up: WorldUp | None = None) -> Path:
        """Write what is buffered, mark the file complete and move it to its final name.

        Args:
            up: the world up found once all rows are in (the ``up`` and ``up_source``
                attributes; the header's up, and the run key, stay as they were), or None
                to keep the header's.
        """
        if self._f is None:
            raise RuntimeError("IncrementalPosesWriter.finish before open()")
        if self._buffered:
            self._commit(self._buffered)
        if self.completed != self.header.num_frames:
            raise RuntimeError(
                f"{self.partial}: only {self.completed} of {self.header.num_frames} rows written"
            )
        out = self._out
        assert out is not None
        try:
            if up is not None:
                out.file.attrs["up"] = up.up
                out.file.attrs["up_source"] = up.source
            out.file.attrs["complete"] = True
            self._out = None
            out.close()
        except OutputWriteError:
            self._out = out
            self._give_up()
            raise
        with output_errors(self.path, self.partial):
            os.replace(self.partial, self.path)
        return self.path

    def close(self) -> None:
        """Close without finishing (rows of unfinished chunks are discarded; resume redoes them).

        A partial file that a failed write damaged is removed (a rerun starts it again).
        """
        if self._out is not None:
            out, self._out = self._out, None
            try:
                out.close()
            except OutputWriteError:
                with contextlib.suppress(OSError):
                    self.partial.unlink(missing_ok=True)

    def __enter__(self) -> IncrementalPosesWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
