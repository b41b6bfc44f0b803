"""Several animals through ``freipose predict --animals N``: tracks first, then poses per animal.

Each session is read twice:

1. **tracking** (:func:`track_session`): a box source with several boxes per view
   (:class:`~freipose.detect.multi.SplitForeground` for background subtraction,
   :class:`~freipose.detect.multi.PeakBoxes` around a trained detector), the association
   of the views' boxes into 3D animal hypotheses and the tracking with motion and coat
   colour (:func:`freipose.predict.animals.track_recording`) over the run's whole frame
   range, in order, then the whole-recording identity pass
   (:mod:`freipose.predict.identity`): who is who in a frame depends on the frames before
   and after it. The tracks cost the box proposals only; a resumed run makes them again.
2. **poses** (:func:`predict_animal_session`): per batch of frames the voxel network on
   each tracked animal's cube, centred on its track (the animals are extra samples of one
   network batch), written by the resumable
   :class:`~freipose.predict.writer.IncrementalPosesWriter` with an animal axis:
   ``individuals`` ``animal_0``, ``animal_1``, ... (the tracks, in the order they were
   first found), ``identity_confidence`` and ``extra/identity_flagged`` (the tracker's
   confidence and its flag where a swap cannot be ruled out or was undone, and the frames
   where two animals' poses lie on each other: one animal found twice,
   :func:`~freipose.predict.identity.coincident_poses`). An animal that its track
   does not match in a frame has NaN poses there; a frame is ``status`` 0 when any animal
   was predicted.
3. **poses' identities** (:func:`freipose.predict.identity.relabel_by_poses`): in close
   contact an animal's cube holds parts of the other, and the two poses can come out
   exchanged for a frame or a few although the tracks were right; once all rows are
   written, the rows are reordered per frame so that every animal's whole pose moves
   continuously (``extra/identity_order``: the track each animal's pose came from; the
   frames where it changes are flagged). A run killed while reordering finishes it when
   started again.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from freipose.geometry.camera import CameraRig
from freipose.io.calibration_world import resolve_up, stored_up_or_z, world_up
from freipose.io.lock import output_lock
from freipose.io.session import Session
from freipose.io.video import frame_range
from freipose.predict.estimator import Estimate, estimate_with_missing
from freipose.predict.identity import coincident_poses, relabel_by_poses
from freipose.predict.network import (
    DetectorSpec,
    NetworkEstimator,
    check_keypoints,
    load_model,
    make_box_source,
    network_provenance,
    resolve_device,
)
from freipose.predict.reader import SyncReader
from freipose.predict.run import (
    CHUNK_FRAMES,
    MIN_VIEWS,
    PredictError,
    PredictResult,
    commit_rows,
    output_path,
    session_provenance,
    status_counts,
)
from freipose.predict.tracking import Tracks
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

ANIMAL_METHODS = ("bgsub", "detector")


def animal_names(n: int) -> tuple[str, ...]:
    """The ``individuals`` of a prediction of ``n`` animals: ``animal_0`` .. ``animal_<n-1>``."""
    return tuple(f"animal_{i}" for i in range(n))


def check_animal_method(spec: DetectorSpec, n_animals: int) -> None:
    """Refuse fewer than two animals, or a detection method with one box per view.

    Raises:
        PredictError: the message says which methods find several animals.
    """
    if n_animals < 2:
        raise PredictError(f"several animals means at least 2, got --animals {n_animals}")
    if spec.method not in ANIMAL_METHODS:
        raise PredictError(
            f"--animals {n_animals} finds the animals with --method bgsub or a --detector, not "
            f"--method {spec.method} (fixed boxes, where auto can end, place one cube between "
            "the animals)"
        )


def animal_box_source(
    spec: DetectorSpec, session: Session, frames: tuple[int, int], n_animals: int, device: str
) -> Any:
    """A box source with up to one box per animal and view (several boxes per view).

    Args:
        spec: how the animals are found: ``bgsub`` (background subtraction split into
            animals) or ``detector`` (the trained detector's best peaks).
        session: the session.
        frames: the run's frame range (the background is fitted on it).
        n_animals: how many animals.
        device: where the detector runs.

    Raises:
        PredictError: another method (fixed boxes and ``auto`` give one box per view).
    """
    from freipose.detect.multi import PeakBoxes, SplitForeground

    check_animal_method(spec, n_animals)
    source = make_box_source(spec, session, frames, device)
    if spec.method == "bgsub":
        return SplitForeground(source, n_animals)
    source.top_k = max(int(source.top_k), n_animals + 2)
    return PeakBoxes(source, max_boxes=n_animals + 2)


def _frames(session: Session, start: int, stop: int, batch: int) -> Iterator[list]:
    """Every frame of ``[start, stop)`` as C images (None where it could not be decoded)."""
    shapes = [(cam.height, cam.width) for cam in session.rig]
    with SyncReader(list(session.videos.values()), start, stop, batch, shapes) as reader:
        for fb in reader:
            for b in range(len(fb)):
                yield [im[b] if ok else None for im, ok in zip(fb.images, fb.valid[b], strict=True)]


def track_session(
    session: Session,
    source: Any,
    n_animals: int,
    frames: tuple[int, int],
    cube_size: float,
    min_views: int = MIN_VIEWS,
    batch: int = 8,
    progress: bool = True,
) -> Tracks:
    """Find, associate and follow ``n_animals`` over the frames ``[start, stop)``.

    Args:
        session: the session.
        source: a box source with several boxes per view (:func:`animal_box_source`).
        n_animals: how many animals (A).
        frames: ``(start, stop)``.
        cube_size: the pose network's cube edge, mm (the animals' crops).
        min_views: fewest agreeing views of an animal.
        batch: frames sent to the box source at once.
        progress: show a progress bar.

    Returns:
        :class:`~freipose.predict.tracking.Tracks` with T = stop - start rows.
    """
    from freipose.detect.multi import AnimalsConfig
    from freipose.predict.animals import track_recording

    cfg = AnimalsConfig(cube_size=cube_size, min_views=min_views, max_animals=n_animals + 1)
    bar = progress_bar(
        _frames(session, frames[0], frames[1], batch), total=frames[1] - frames[0],
        unit="frame", desc=f"{session.name}: tracking", disable=not progress or None, leave=False,
    )  # fmt: skip
    with bar:
        res = track_recording(bar, session.rig, source, n_animals, session.fps, cfg,
                              chunk=batch, keep=False)  # fmt: skip
    return res.tracks


@dataclass(frozen=True, eq=False)
class _AtCentres:
    """An estimator for :func:`estimate_with_missing` over samples with known cube centres.

    Sample ``i`` of the batch has the centre ``centres[i]``; the rows of a call are those
    whose decoded cameras are the call's cameras (how ``estimate_with_missing`` groups).
    """

    network: NetworkEstimator
    centres: np.ndarray
    valid: np.ndarray
    rig: CameraRig
    animals: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def keypoints(self) -> tuple[str, ...]:
        return self.network.keypoints

    @property
    def provenance(self) -> dict[str, Any]:
        return self.network.provenance

    def __call__(self, images: Sequence[np.ndarray], rig: CameraRig) -> Estimate:
        shown = np.isin(self.rig.names, rig.names)
        rows = np.flatnonzero((self.valid == shown).all(1))
        frames = [[images[c][i] for c in range(len(rig))] for i in range(len(rows))]
        if self.animals is None:
            return self.network.predict_at(frames, rig, self.centres[rows])
        cues = (self.animals[0][rows], self.animals[1][rows])
        return self.network.predict_at(frames, rig, self.centres[rows], animals=cues)


def _pass_animals(poses: np.ndarray, a_n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per row (animal-major), its own pose and the other animals' at its frame.

    Args:
        poses: (A*B, K, 3) a pass's poses, row ``a * B + b``.
        a_n: the number of animals A.

    Returns:
        ``(own, others)``: (A*B, K, 3) and (A*B, A-1, K, 3).
    """
    per = poses.reshape(a_n, -1, *poses.shape[1:])  # (A, B, K, 3)
    others = np.stack([np.delete(per, a, axis=0).swapaxes(0, 1) for a in range(a_n)])
    return poses, others.reshape(-1, a_n - 1, *poses.shape[1:])


def estimate_animals(
    network: NetworkEstimator,
    images: Sequence[np.ndarray],
    valid: np.ndarray,
    rig: CameraRig,
    centres: np.ndarray,
) -> tuple[list[Estimate], np.ndarray]:
    """The network on every animal's cube of B frames, the animals as extra samples.

    With ``model.mask_others`` the network runs again ``model.mask_passes`` times, each
    animal's views with the other animals painted out at the previous pass's poses.

    Args:
        network: the pose network.
        images: C arrays (B, H_c, W_c, 3) BGR.
        valid: (B, C) the decoded frames.
        rig: the C cameras.
        centres: (B, A, 3) world mm cube centres per frame and animal (NaN: not found).

    Returns:
        ``(estimates, ran)``: A estimates of B rows, and (B,) whether the frame had at least
        two decoded cameras.
    """
    b_n, a_n = centres.shape[:2]
    tiled = [np.concatenate([im] * a_n) for im in images]  # animal-major: row a * B + b
    flat = np.asarray(centres, np.float64).transpose(1, 0, 2).reshape(a_n * b_n, 3)
    valid_t = np.tile(np.asarray(valid, bool), (a_n, 1))
    est, ran = estimate_with_missing(
        _AtCentres(network, flat, valid_t, rig), tiled, valid_t, rig, MIN_VIEWS
    )
    cfg = getattr(getattr(network, "model", None), "cfg", None)
    for _ in range(cfg.mask_passes if getattr(cfg, "mask_others", False) and a_n > 1 else 0):
        # again with the other animals painted out, at the previous pass's poses
        est, ran = estimate_with_missing(
            _AtCentres(network, flat, valid_t, rig, _pass_animals(est.poses, a_n)),
            tiled, valid_t, rig, MIN_VIEWS,
        )  # fmt: skip
    parts = []
    for a in range(a_n):
        sl = slice(a * b_n, (a + 1) * b_n)
        u = None if est.uncertainty is None else est.uncertainty[sl]
        parts.append(Estimate(est.poses[sl], est.confidence[sl], est.points2d[sl],
                              est.confidence2d[sl], est.boxes[sl], est.center[sl], u))  # fmt: skip
    return parts, ran[:b_n]


@dataclass(frozen=True)
class AnimalRun:
    """One session's run of several animals.

    Attributes:
        network: the pose network (its ``source`` is not used).
        source: the box source with several boxes per view.
        n_animals: how many animals.
        start, stop: the frame range.
        batch_size: frames per network call (times the animals: samples).
        chunk_frames: rows per committed chunk.
        skeleton: stored with the poses.
        overwrite: redo a complete output, never resume a partial one.
        progress: show progress bars.
    """

    network: NetworkEstimator
    source: Any
    n_animals: int
    start: int
    stop: int
    batch_size: int = 8
    chunk_frames: int = CHUNK_FRAMES
    skeleton: Skeleton | None = None
    overwrite: bool = False
    progress: bool = True


def predict_animal_session(session: Session, run: AnimalRun, outdir: str | Path) -> PredictResult:
    """Track the animals of one session and predict each one's poses (module docstring).

    Returns:
        A :class:`~freipose.predict.run.PredictResult` for ``OUTDIR/<session>.poses.h5``.

    Raises:
        OutputLockedError: another run is writing the same output.
    """
    t0 = time.perf_counter()
    path = output_path(outdir, session.name)
    with output_lock(path, "poses file"):
        if path.exists() and not run.overwrite:
            if is_complete(path):
                log.info("%s exists and is complete; skipping (use --overwrite to redo it)", path)
                return PredictResult(path=path, skipped=True)
            log.warning("%s exists but is not a complete output; redoing it", path)
        header = OutputHeader(
            keypoints=run.network.keypoints, rig=session.rig, start=run.start, stop=run.stop,
            fps=session.fps, skeleton=run.skeleton,
            provenance=session_provenance(session, run.network, {"animals": run.n_animals}),
            up=tuple(stored_up_or_z(session.rig).tolist()),
            individuals=animal_names(run.n_animals),
        )  # fmt: skip
        writer = IncrementalPosesWriter(path, header, commit_rows(run.batch_size, run.chunk_frames))
        try:
            done = writer.open(fresh=run.overwrite)
            tracks = track_session(session, run.source, run.n_animals, (run.start, run.stop),
                                   run.network.cube_size, run.network.consistency.min_views,
                                   run.batch_size, run.progress)  # fmt: skip
            frames, missing = _predict_rows(session, run, tracks, writer, done)
            order = writer.stored_animal_order()
            if order is None:
                order = relabel_by_poses(writer.poses(), session.fps).order
            writer.reorder_animals(order)
            up = None
            if world_up(session.rig) is None:
                k = len(header.keypoints)
                up = resolve_up(session.rig, writer.poses().reshape(-1, k, 3),
                                "the poses' up attribute", what="predicted")  # fmt: skip
            out = writer.finish(up=up)
        finally:
            writer.close()
    return PredictResult(path=out, frames=frames, seconds=time.perf_counter() - t0,
                         missing=missing, status_counts=status_counts(out))  # fmt: skip


def _predict_rows(
    session: Session, run: AnimalRun, tracks: Tracks, writer: IncrementalPosesWriter, done: int
) -> tuple[int, dict[str, int]]:
    """Predict and write the rows ``done ..`` of the run.

    Returns:
        ``(rows written, camera -> first frame that could not be decoded)``.
    """
    shapes = [(cam.height, cam.width) for cam in session.rig]
    n = 0
    bar = progress_bar(total=run.stop - run.start, initial=done, unit="frame", desc=session.name,
                       disable=not run.progress or None, leave=False)  # fmt: skip
    videos = list(session.videos.values())
    with (
        bar,
        SyncReader(
            videos, run.start + done, run.stop, run.batch_size, shapes, align=run.start
        ) as reader,  # fmt: skip
    ):
        for fb in reader:
            rows = fb.frame_index - run.start
            ests, ran = estimate_animals(
                run.network, fb.images, fb.valid, session.rig, tracks.centers[rows]
            )
            found = np.stack([np.isfinite(e.poses).all(-1).any(-1) for e in ests]).any(0)
            status = np.where(~ran, STATUS_FEW_VIEWS, np.where(found, STATUS_OK, STATUS_NOT_FOUND))
            twice = coincident_poses(np.stack([e.poses for e in ests], 1))  # one animal twice
            writer.add_animals(ests, status, fb.valid, tracks.confidence[rows],
                               tracks.flagged[rows] | twice)  # fmt: skip
            n += len(fb)
            bar.update(len(fb))
        missing = {session.rig.names[c]: i for c, i in sorted(reader.first_missing.items())}
    return n, missing


def predict_animal_sessions(
    sessions: Sequence[Session],
    model_path: str | Path,
    spec: DetectorSpec,
    outdir: str | Path,
    n_animals: int,
    *,
    frames: str | None = None,
    batch_size: int = 8,
    device: str = "auto",
    refine: bool = True,
    overrides: Any = None,
    backend: str = "auto",
    chunk_frames: int = CHUNK_FRAMES,
    overwrite: bool = False,
    expected_skeleton: Skeleton | None = None,
    progress: bool = True,
    report: Any = None,
) -> list[PredictResult]:
    """Predict the poses of ``n_animals`` animals in every session (``freipose predict --animals``).

    Arguments as :func:`freipose.predict.network.predict_sessions`, plus ``n_animals``
    (>= 2). The model, its keypoints and the detection method are checked before any frame
    is read.

    Raises:
        PredictError: fewer than two animals, or a detection method that gives one box per
            view.
    """
    check_animal_method(spec, n_animals)
    dev = resolve_device(device)
    ranges = {s.name: frame_range(frames, s.num_frames) for s in sessions}
    net, config, skel, sha = load_model(model_path, dev, overrides, backend)
    check_keypoints(skel, expected_skeleton, model_path)
    provenance, scale = network_provenance(net, config, sha, model_path, spec, refine)
    results = []
    for s in sessions:
        r = ranges[s.name]
        out = output_path(outdir, s.name)
        if out.exists() and is_complete(out) and not overwrite:
            log.info("%s exists and is complete; skipping (use --overwrite to redo it)", out)
            res = PredictResult(path=out, skipped=True)
        else:
            source = animal_box_source(spec, s, (r.start, r.stop), n_animals, dev)
            network = NetworkEstimator(net, config, skel, None, refine, provenance,
                                       spec.min_views, scale)  # fmt: skip
            run = AnimalRun(network, source, n_animals, r.start, r.stop, batch_size,
                            chunk_frames, skel, overwrite, progress)  # fmt: skip
            res = predict_animal_session(s, run, outdir)
        if report is not None:
            report(res)
        results.append(res)
    return results


__all__ = [
    "AnimalRun",
    "animal_box_source",
    "animal_names",
    "check_animal_method",
    "estimate_animals",
    "predict_animal_session",
    "predict_animal_sessions",
    "track_session",
]
