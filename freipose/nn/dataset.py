"""A PyTorch ``Dataset`` over ``labels.h5``: one sample per labeled time instant.

Each sample (:class:`freipose.nn.types.Sample`) holds the frames of all of the session's
cameras (read from the session videos with :class:`freipose.io.video.FrameSource`: random
access and an LRU cache of decoded frames), the session's cameras, and the 2D/3D labels
with masks; :func:`labeled_sample` builds it.

The views of a session are the cameras of its calibration (in calibration order) that
have a video, optionally restricted to ``cameras``; with ``load_images=False`` a session
that lists no videos at all uses every calibrated camera. Sessions may have different
rigs and numbers of cameras, so batches are lists: use ``collate_fn=list_collate``.

Videos are opened lazily in the process that reads them (so ``DataLoader`` workers each
open their own), and errors are clear: a missing video or a frame index past a video's
end raises :class:`LabelsDataError` naming the file.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch.utils.data

from freipose.errors import FreiPoseError
from freipose.geometry.camera import CameraRig
from freipose.io.calibration_world import rig_with_up
from freipose.io.labels import LabelSet, read_labels_h5
from freipose.io.video import FrameSource, MediaError
from freipose.nn.types import Sample

log = logging.getLogger(__name__)


CACHE_BYTES = 3 * 2**30
"""Decoded frames a dataset keeps by default, per process: every labeled frame of every
video when they fit in this many bytes and an eighth of the machine's memory (training
visits each many times), else :data:`CACHE_FRAMES` per video."""
CACHE_FRAMES = 64


def cache_budget() -> int:
    """Bytes of decoded frames a dataset may keep.

    :data:`CACHE_BYTES`, at most an eighth of the machine's physical memory (where the
    system tells it).
    """
    try:
        physical = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):
        return CACHE_BYTES
    return min(CACHE_BYTES, physical // 8) if physical > 0 else CACHE_BYTES


class LabelsDataError(FreiPoseError):
    """A sample cannot be assembled (missing video, frame past a video's end, ...)."""


def list_collate(batch: list[Sample]) -> list[Sample]:
    """Collate function for samples with variable numbers of views: the list itself.

    Args:
        batch: samples from :class:`MultiViewDataset`.

    Returns:
        The samples as a list.
    """
    return list(batch)


def other_rows(instants: Sequence[tuple[str, int]]) -> list[np.ndarray]:
    """Per row, the other rows of the same instant: the other animals at its frame.

    Args:
        instants: per row, its (session, frame).

    Returns:
        Per row, the (int64) indices of the other rows with the same (session, frame).
    """
    at: dict[tuple[str, int], list[int]] = {}
    for r, key in enumerate(instants):
        at.setdefault(key, []).append(r)
    return [np.array([o for o in at[key] if o != r], np.int64) for r, key in enumerate(instants)]


def labeled_sample(
    rig: CameraRig | None,
    images: list[np.ndarray],
    points2d: np.ndarray,
    points3d: np.ndarray,
    *,
    visible2d: np.ndarray | None = None,
    camera_names: tuple[str, ...] | None = None,
    session: str = "",
    frame_index: int = 0,
    index: int = 0,
) -> Sample:
    """One multi-view sample (:class:`~freipose.nn.types.Sample`) from its labels.

    Args:
        rig: the V cameras (None without a calibration).
        images: V BGR uint8 (H, W, 3) full frames (``[]`` without images).
        points2d: (V, K, 2) full-image pixels, NaN where unlabeled.
        points3d: (K, 3) mm, NaN where unknown.
        visible2d: (V, K) bool visibility of the 2D labels (default: every finite label).
        camera_names: the names of the V views (default: the rig's).
        session: the session's name.
        frame_index: the frame of the session's videos.
        index: the sample's index in its dataset.

    Returns:
        The sample; ``visible2d`` is False and ``mask3d`` False where a label is not finite.
    """
    finite2 = np.isfinite(points2d).all(-1)
    vis = finite2 if visible2d is None else (visible2d & finite2)
    if camera_names is None:
        camera_names = tuple(rig.names) if rig is not None else ()
    return {
        "session": session,
        "frame_index": frame_index,
        "index": index,
        "rig": rig,
        "camera_names": camera_names,
        "images": images,
        "points2d": points2d,
        "visible2d": vis,
        "points3d": points3d,
        "mask3d": np.isfinite(points3d).all(-1),
    }


class MultiViewDataset(torch.utils.data.Dataset):
    """Multi-view training samples from a labels file (see the module docstring).

    Args:
        labels: a :class:`LabelSet` or the path of a ``labels.h5`` file.
        root: the folder video paths are relative to (default: the labels file's folder,
            or the current folder when ``labels`` is a ``LabelSet``).
        cameras: use only these cameras (names); others are dropped from every sample.
        cache_size: decoded frames kept per video (least recently used); None (default):
            every labeled frame when all of them take at most :func:`cache_budget` (read
            in one forward pass through each video when it is first used), else
            :data:`CACHE_FRAMES`.
        load_images: read the frames; with False, ``images`` is ``[]`` and no video is
            opened (labels and cameras only).

    Raises:
        LabelsDataError: a requested camera is unknown, or a session has no usable view.
    """

    def __init__(
        self,
        labels: LabelSet | str | Path,
        root: Path | None = None,
        cameras: Sequence[str] | None = None,
        cache_size: int | None = None,
        load_images: bool = True,
    ):
        if isinstance(labels, LabelSet):
            self.labels = labels
            self.root = Path(root) if root is not None else Path.cwd()
        else:
            path = Path(labels)
            self.labels = read_labels_h5(path)
            self.root = Path(root) if root is not None else path.resolve().parent
        self.load_images = bool(load_images)
        # with several animals: the rows of the other animals at each row's instant
        lab = self.labels
        self._others = (
            None
            if lab.individual is None
            else other_rows([(str(s), int(f)) for s, f in zip(lab.session, lab.frame_index)])
        )
        all_cams = self.labels.cameras
        if cameras is not None:
            unknown = [c for c in cameras if c not in all_cams]
            if unknown:
                raise LabelsDataError(
                    f"cameras {unknown} are not in the labels (its cameras: {list(all_cams)})"
                )
        wanted = None if cameras is None else set(cameras)
        # Per session: the view names, their columns in the label arrays, the rig, videos.
        self._views: dict[str, tuple[tuple[str, ...], np.ndarray, CameraRig | None]] = {}
        self._video_paths: dict[tuple[str, str], Path] = {}
        for s in sorted(set(self.labels.session)):
            info = self.labels.sessions.get(s)
            videos = dict(info.videos) if info is not None else {}
            rig = info.calibration if info is not None else None
            order = list(rig.names) if rig is not None else list(all_cams)
            names = [c for c in order if c in videos] if self.load_images or videos else order
            if wanted is not None:
                names = [c for c in names if c in wanted]
            if not names:
                raise LabelsDataError(
                    f"session {s!r} has no usable camera view: calibration cameras {order}, "
                    f"videos for {sorted(videos)}"
                    + ("" if wanted is None else f", restricted to {sorted(wanted)}")
                    + "; add the videos to the labels file (or use load_images=False)"
                )
            cols = np.array([all_cams.index(c) for c in names], dtype=np.int64)
            sub = rig.subset(names) if rig is not None else None
            if sub is not None:  # the grid rotation turns about the world's up
                pts = self.labels.points3d[np.asarray(self.labels.session) == s]
                sub = rig_with_up(sub, pts, f"session {s!r}'s grid rotation")
            self._views[s] = (tuple(names), cols, sub)
            for c in names:
                if c in videos:
                    p = Path(videos[c])
                    self._video_paths[(s, c)] = p if p.is_absolute() else self.root / p
        session = np.asarray(self.labels.session)
        self._labeled_frames = {
            s: np.unique(self.labels.frame_index[session == s]) for s in self._views
        }
        self.cache_size = self._cache_frames() if cache_size is None else int(cache_size)
        # Filling the cache in the order training visits the frames seeks the video for each
        # one; when every labeled frame is kept they are decoded in one forward pass instead.
        self._prefill = cache_size is None and all(
            len(f) <= self.cache_size for f in self._labeled_frames.values()
        )
        self._sources: dict[tuple[str, str], FrameSource] = {}
        self._inherited: list[FrameSource] = []
        self._pid = os.getpid()

    def __len__(self) -> int:
        return len(self.labels)

    def _cache_frames(self) -> int:
        """Frames to cache per video: the most any video has labeled, if all fit the budget."""
        frames = {s: len(f) for s, f in self._labeled_frames.items()}
        total = 0
        for s, c in self._video_paths:
            rig = self._views[s][2]
            if rig is None:
                return CACHE_FRAMES
            total += frames[s] * int(rig[c].width) * int(rig[c].height) * 3
        most = max((frames[s] for s, _ in self._video_paths), default=0)
        return max(most, CACHE_FRAMES) if total <= cache_budget() else CACHE_FRAMES

    # Sources are per process: after fork or unpickling in a worker they are reopened.
    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_sources"] = {}
        state["_inherited"] = []
        return state

    def _source(self, session: str, camera: str) -> FrameSource:
        if self._pid != os.getpid():
            # A forked worker: the parent's decoders must not be used, and must not be
            # released here either (FFmpeg may hold locks copied mid-operation by fork, so
            # releasing them can deadlock). Keep them alive and open new ones.
            self._inherited.extend(self._sources.values())
            self._sources = {}
            self._pid = os.getpid()
        key = (session, camera)
        src = self._sources.get(key)
        if src is None:
            path = self._video_paths.get(key)
            if path is None:
                raise LabelsDataError(f"session {session!r} lists no video for camera {camera!r}")
            try:
                src = FrameSource(path, cache_size=self.cache_size)
            except MediaError as exc:
                raise LabelsDataError(
                    f"session {session!r}, camera {camera!r}: {exc} (video paths are relative "
                    f"to {self.root}; to change that, set `data.root` in the training config "
                    "or pass --root to `freipose eval`)"
                ) from exc
            self._sources[key] = src
            if self._prefill:
                self._read_ahead(src, self._labeled_frames[session])
        return src

    @staticmethod
    def _read_ahead(src: FrameSource, frames: np.ndarray) -> None:
        """Decode ``frames`` (ascending) into ``src``'s cache in one forward pass.

        A frame past the video's end or one that cannot be decoded stops it; reading that
        sample raises the error that names it.
        """
        for f in frames:
            if f >= src.num_frames:
                return
            try:
                src.read(int(f))
            except MediaError:
                return

    def __getitem__(self, i: int) -> Sample:
        n = len(self)
        if not -n <= int(i) < n:
            raise IndexError(f"sample {i} is outside 0..{n - 1}")
        i = int(i) % n
        lab = self.labels
        s = str(lab.session[i])
        fi = int(lab.frame_index[i])
        names, cols, rig = self._views[s]
        p2 = lab.points2d[i, cols].copy()
        vis = None if lab.visible2d is None else lab.visible2d[i, cols]
        p3 = lab.points3d[i].copy()
        images: list[np.ndarray] = []
        if self.load_images:
            for c in names:
                src = self._source(s, c)
                try:
                    images.append(src.read(fi))
                except IndexError as exc:
                    # Not IndexError: that would silently end iteration over the dataset.
                    raise LabelsDataError(
                        f"{src.path}: label {i} (session {s!r}) asks for frame {fi}, but the "
                        f"video has {src.num_frames} frames (0..{src.num_frames - 1}); the "
                        f"labels do not belong to this video or it is truncated"
                    ) from exc
                except MediaError as exc:
                    raise LabelsDataError(f"session {s!r}, camera {c!r}: {exc}") from exc
        sample = labeled_sample(
            rig,
            images,
            p2,
            p3,
            visible2d=vis,
            camera_names=names,
            session=s,
            frame_index=fi,
            index=i,
        )
        if self._others is not None:
            sample["others3d"] = lab.points3d[self._others[i]].copy()
        return sample

    def validate(self) -> None:
        """Open every video once and check every labeled frame index lies inside it.

        Raises:
            LabelsDataError: a video is missing/unreadable or too short (message names it).
        """
        for (s, c), _ in sorted(self._video_paths.items()):
            src = self._source(s, c)
            fis = self.labels.frame_index[self.labels.session == s]
            if len(fis) and int(fis.max()) >= src.num_frames:
                raise LabelsDataError(
                    f"{src.path}: session {s!r} has labels at frame {int(fis.max())}, but the "
                    f"video has only {src.num_frames} frames; the labels do not belong to "
                    f"this video or it is truncated"
                )
            if len(fis) and int(fis.min()) < 0:
                raise LabelsDataError(f"session {s!r}: negative frame index {int(fis.min())}")

    def close(self) -> None:
        """Release the open videos."""
        for src in self._sources.values():
            src.close()
        self._sources = {}
