"""The prediction loop: session videos -> ``<session>.poses.h5``, resumable and shardable.

Decoding runs ahead in background threads (:class:`~freipose.predict.reader.SyncReader`),
the estimator runs on batches of synchronized frames in the calling thread, and the
:class:`~freipose.predict.writer.IncrementalPosesWriter` commits whole chunks. Batches and
chunks are aligned to the start of the run's frame range, and shard boundaries to whole
chunks, so a resumed run and the merged shards process exactly the same batches as an
uninterrupted single run and give the same numbers.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from freipose import __version__
from freipose.errors import FreiPoseError
from freipose.geometry.camera import CameraRig
from freipose.io.calibration_world import WorldUp, resolve_up, stored_up_or_z, world_up
from freipose.io.lock import output_lock
from freipose.io.session import Session
from freipose.io.video import frame_range
from freipose.predict.estimator import PoseEstimator, estimate_with_missing
from freipose.predict.reader import SyncReader
from freipose.predict.writer import (
    STATUS_FEW_VIEWS,
    STATUS_NOT_FOUND,
    STATUS_OK,
    IncrementalPosesWriter,
    OutputHeader,
    is_complete,
)
from freipose.progress import progress_bar
from freipose.skeleton import Skeleton

log = logging.getLogger(__name__)

CHUNK_FRAMES = 256
MIN_VIEWS = 2


class PredictError(FreiPoseError):
    """A prediction run cannot start as asked (bad shard, frames or skeleton)."""


def parse_shard(spec: str | None) -> tuple[int, int] | None:
    """``"i/n"`` (0 <= i < n) -> (i, n); None stays None.

    Raises:
        PredictError: malformed spec.
    """
    if spec is None or spec == "":
        return None
    try:
        i_s, n_s = spec.split("/")
        i, n = int(i_s), int(n_s)
    except ValueError:
        raise PredictError(f"--shard must look like I/N (e.g. 0/4), got {spec!r}") from None
    if n < 1 or not 0 <= i < n:
        raise PredictError(f"--shard {spec!r}: need 0 <= I < N (shards are numbered from 0)")
    return i, n


def commit_rows(batch_size: int, chunk_frames: int = CHUNK_FRAMES) -> int:
    """Rows per committed chunk: the smallest multiple of the batch size >= ``chunk_frames``."""
    return batch_size * max(1, math.ceil(chunk_frames / batch_size))


def shard_range(
    start: int, stop: int, shard: tuple[int, int] | None, align: int
) -> tuple[int, int]:
    """The contiguous part ``[a, b)`` of ``[start, stop)`` that shard ``(i, n)`` processes.

    Boundaries fall on multiples of ``align`` frames from ``start``; shards may be empty when
    there are fewer aligned blocks than shards.
    """
    if shard is None:
        return start, stop
    i, n = shard
    blocks = math.ceil((stop - start) / align)
    b0 = (blocks * i) // n
    b1 = (blocks * (i + 1)) // n
    return min(start + b0 * align, stop), min(start + b1 * align, stop)


def output_path(outdir: str | Path, session: str, shard: tuple[int, int] | None = None) -> Path:
    """``OUTDIR/<session>.poses.h5``, or ``OUTDIR/<session>.shard-I-of-N.poses.h5``."""
    outdir = Path(outdir)
    if shard is None:
        return outdir / f"{session}.poses.h5"
    return outdir / f"{session}.shard-{shard[0]}-of-{shard[1]}.poses.h5"


@dataclass(frozen=True, eq=False)
class PredictResult:
    """What happened to one session.

    Attributes:
        path: the output file.
        skipped: the output existed and was complete (nothing was done).
        frames: number of frames predicted in this call.
        seconds: wall time of this call.
        missing: camera -> first frame that could not be decoded (the rest of that camera's
            frames are missing); empty when every frame was read.
        status_counts: status name -> number of frames in the output.
    """

    path: Path
    skipped: bool = False
    frames: int = 0
    seconds: float = 0.0
    missing: Mapping[str, int] = field(default_factory=dict)
    status_counts: Mapping[str, int] = field(default_factory=dict)


def session_provenance(
    session: Session, estimator: PoseEstimator, extra: Mapping[str, Any] | None
) -> dict:
    """Facts stored in the output (no paths, times or host names: shards must agree)."""
    prov: dict[str, Any] = {
        "freipose_version": __version__,
        "session": session.name,
        "videos": {c: Path(p).name for c, p in session.videos.items()},
        "fps": session.fps,
    }
    prov.update(dict(estimator.provenance))
    if extra:
        prov.update(extra)
    return prov


@dataclass(frozen=True)
class _RunPlan:
    """The frames one call processes.

    Attributes:
        start: first frame of the whole run (batches and chunks align to it).
        stop: end (exclusive) of the whole run.
        a: first frame of this call's shard.
        b: end (exclusive) of this call's shard.
        rows_per_chunk: rows per committed chunk.
    """

    start: int
    stop: int
    a: int
    b: int
    rows_per_chunk: int


def _plan_run(
    session: Session,
    frames: str | tuple[int, int] | None,
    batch_size: int,
    chunk_frames: int,
    shard: tuple[int, int] | None,
) -> _RunPlan:
    """The run's frame range and this shard's part of it, aligned to whole chunks."""
    if isinstance(frames, tuple):
        start, stop = frames
    else:
        r = frame_range(frames, session.num_frames)
        start, stop = r.start, r.stop
    rows_per_chunk = commit_rows(batch_size, chunk_frames)
    a, b = shard_range(start, stop, shard, rows_per_chunk)
    return _RunPlan(start, stop, a, b, rows_per_chunk)


@dataclass(frozen=True)
class _LoopResult:
    """What the frame loop did.

    Attributes:
        frames: rows written in this call.
        missing: camera -> first frame that could not be decoded.
    """

    frames: int
    missing: dict[str, int]


def _predict_frames(
    session: Session,
    estimator: PoseEstimator,
    writer: IncrementalPosesWriter,
    plan: _RunPlan,
    done: int,
    batch_size: int,
    progress: bool,
    prefetch: int,
    on_batch: Callable[[int], None] | None,
) -> _LoopResult:
    """Estimate and write the frames ``plan.a + done .. plan.b`` batch by batch."""
    done_now = 0
    shapes = [(cam.height, cam.width) for cam in session.rig]
    bar = progress_bar(
        total=plan.b - plan.a,
        initial=done,
        unit="frame",
        desc=session.name,
        disable=not progress or None,
        leave=False,
    )
    with (
        bar,
        SyncReader(
            list(session.videos.values()),
            plan.a + done,
            plan.b,
            batch_size,
            shapes,
            align=plan.start,
            prefetch=prefetch,
        ) as reader,
    ):
        for fb in reader:
            est, ran = estimate_with_missing(estimator, fb.images, fb.valid, session.rig, MIN_VIEWS)
            found = np.isfinite(est.poses).all(-1).any(-1)
            status = np.where(~ran, STATUS_FEW_VIEWS, np.where(found, STATUS_OK, STATUS_NOT_FOUND))
            writer.add(est, status, fb.valid)
            done_now += len(fb)
            bar.update(len(fb))
            if on_batch is not None:
                on_batch(done + done_now)
        missing = {session.rig.names[c]: i for c, i in sorted(reader.first_missing.items())}
    return _LoopResult(done_now, missing)


def _warn_missing(session: Session, missing: Mapping[str, int], stop: int) -> None:
    """Log the cameras whose video ended early (frames ``i .. stop - 1`` undecodable)."""
    for cam, i in missing.items():
        log.warning(
            "session %r: camera %r: frames %d..%d could not be decoded (truncated or damaged "
            "video?); they are predicted from the other cameras where at least %d remain, else "
            "NaN with status %d",
            session.name,
            cam,
            i,
            stop - 1,
            MIN_VIEWS,
            STATUS_FEW_VIEWS,
        )


def predict_session(
    session: Session,
    estimator: PoseEstimator,
    outdir: str | Path,
    *,
    frames: str | tuple[int, int] | None = None,
    batch_size: int = 8,
    shard: tuple[int, int] | None = None,
    overwrite: bool = False,
    skeleton: Skeleton | None = None,
    provenance: Mapping[str, Any] | None = None,
    chunk_frames: int = CHUNK_FRAMES,
    progress: bool = True,
    prefetch: int = 3,
    on_batch: Callable[[int], None] | None = None,
) -> PredictResult:
    """Predict one session into ``OUTDIR/<session>.poses.h5`` (or its shard file).

    Args:
        session: a validated session.
        estimator: frames -> poses.
        outdir: output folder.
        frames: ``"START:STOP"`` or (start, stop); default all frames.
        batch_size: time steps per estimator call.
        shard: (i, n) to process only the i-th of n contiguous parts of the frames.
        overwrite: redo an output that exists and is complete (default: skip it), and
            never resume a partial file of an interrupted run.
        skeleton: stored with the poses (its keypoints must be the estimator's).
        provenance: further facts to store (e.g. settings such as ``refine``).
        chunk_frames: rows per committed chunk (rounded up to a multiple of ``batch_size``).
        progress: show a progress bar (frames per second, ETA).
        prefetch: batches decoded ahead of the estimator.
        on_batch: called with the number of rows written so far after each batch (tests use
            it to simulate a kill).

    Returns:
        A :class:`PredictResult`.

    Raises:
        PredictError: the skeleton's keypoints are not the estimator's.
        OutputLockedError: another run is writing the same output (nothing is touched).
    """
    t0 = time.perf_counter()
    plan = _plan_run(session, frames, batch_size, chunk_frames, shard)
    path = output_path(outdir, session.name, shard)
    with output_lock(path, "poses file"):
        return _predict_locked(
            session, estimator, path, plan, t0, batch_size=batch_size, shard=shard,
            overwrite=overwrite, skeleton=skeleton, provenance=provenance, progress=progress,
            prefetch=prefetch, on_batch=on_batch,
        )  # fmt: skip


def _predict_locked(
    session: Session,
    estimator: PoseEstimator,
    path: Path,
    plan: _RunPlan,
    t0: float,
    *,
    batch_size: int,
    shard: tuple[int, int] | None,
    overwrite: bool,
    skeleton: Skeleton | None,
    provenance: Mapping[str, Any] | None,
    progress: bool,
    prefetch: int,
    on_batch: Callable[[int], None] | None,
) -> PredictResult:
    """:func:`predict_session` once the output's lock is held (arguments as there)."""
    if path.exists() and not overwrite:
        if is_complete(path):
            log.info("%s exists and is complete; skipping (use --overwrite to redo it)", path)
            return PredictResult(path=path, skipped=True)
        log.warning("%s exists but is not a complete output; redoing it", path)
    if skeleton is not None and tuple(skeleton.keypoints) != tuple(estimator.keypoints):
        raise PredictError(
            f"skeleton {skeleton.name!r} has keypoints {list(skeleton.keypoints)} but the model "
            f"predicts {list(estimator.keypoints)}"
        )
    header = OutputHeader(
        keypoints=tuple(estimator.keypoints),
        rig=session.rig,
        start=plan.a,
        stop=plan.b,
        fps=session.fps,
        skeleton=skeleton,
        provenance=session_provenance(session, estimator, provenance),
        up=tuple(stored_up_or_z(session.rig).tolist()),  # final unless estimated at the end
        run_start=plan.start,
        run_stop=plan.stop,
        shard=shard,
    )
    writer = IncrementalPosesWriter(path, header, plan.rows_per_chunk)
    try:
        done = writer.open(fresh=overwrite)
        loop = _predict_frames(
            session, estimator, writer, plan, done, batch_size, progress, prefetch, on_batch
        )
        out = writer.finish(up=_predicted_up(session.rig, writer, shard))
    finally:
        writer.close()
    _warn_missing(session, loop.missing, plan.b)
    return PredictResult(
        path=out,
        frames=loop.frames,
        seconds=time.perf_counter() - t0,
        missing=loop.missing,
        status_counts=status_counts(out),
    )


def _predicted_up(
    rig: CameraRig, writer: IncrementalPosesWriter, shard: tuple[int, int] | None = None
) -> WorldUp | None:
    """Without a stored up: the one the predicted poses determine, else world z (flagged).

    The estimate is kept only when the poses determine it to within a few degrees
    (:func:`resolve_up`, whose warning says which it is). A shard estimates nothing from
    its own few frames: it stores world z flagged as unknown, and merging the shards
    estimates the up from all their frames. None when the calibration stores an up (the
    header's is final).
    """
    if world_up(rig) is not None:
        return None
    if shard is not None:
        return WorldUp(
            np.array([0.0, 0.0, 1.0]),
            "unknown: world z assumed in every shard; freipose merge estimates the up "
            "from all the frames",
        )
    return resolve_up(rig, writer.poses(), "the poses' up attribute", what="predicted")


STATUS_NAMES = {
    STATUS_OK: "predicted",
    STATUS_NOT_FOUND: "not found",
    STATUS_FEW_VIEWS: "too few views",
}


def status_counts(path: Path) -> dict[str, int]:
    """Frames of a finished poses file per status name (``STATUS_NAMES``)."""
    import h5py

    with h5py.File(path, "r") as f:
        st = f["extra/status"][()]
    return {name: int((st == code).sum()) for code, name in STATUS_NAMES.items()}
