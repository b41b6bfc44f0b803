"""A PyTorch ``Dataset`` over ``labels.h5``: one sample per labeled time instant.

Each sample holds the frames of all of the session's cameras (read from the session
videos with :class:`freipose.io.video.FrameSource`: random access and an LRU cache of
decoded frames), the session's cameras, and the 2D/3D labels with masks::

    {
      "session": str, "frame_index": int, "index": int,
      "rig": CameraRig | None,      # the session's cameras used here, in this order
                                    # (None for a 2D-only session without calibration)
      "camera_names": tuple[str],   # the names of those views (also for 2D-only sessions)
      "images": list[np.ndarray],   # per view BGR uint8 (H, W, 3) full original frames;
                                    # [] with load_images=False
      "points2d": (V, K, 2) float64 original-image pixels, NaN = unlabeled,
      "visible2d": (V, K) bool,     # labeled and visible
      "points3d": (K, 3) float64 mm, NaN = unknown,
      "mask3d": (K,) bool,          # finite points3d
    }

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

from freipose.geometry.camera import CameraRig
from freipose.io.labels import LabelSet, read_labels_h5
from freipose.io.video import FrameSource, MediaError

log = logging.getLogger(__name__)


class LabelsDataError(ValueError):
    """A sample cannot be assembled (missing video, frame past a video's end, ...)."""


def list_collate(batch: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Collate function for samples with variable numbers of views: the list itself."""
    return list(batch)


class MultiViewDataset(torch.utils.data.Dataset):
    """Multi-view training samples from a labels file (see the module docstring).

    Args:
        labels: a :class:`LabelSet` or the path of a ``labels.h5`` file.
        root: the folder video paths are relative to (default: the labels file's folder,
            or the current folder when ``labels`` is a ``LabelSet``).
        cameras: use only these cameras (names); others are dropped from every sample.
        cache_size: decoded frames kept per video (least recently used).
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
        cache_size: int = 64,
        load_images: bool = True,
    ):
        if isinstance(labels, LabelSet):
            self.labels = labels
            self.root = Path(root) if root is not None else Path.cwd()
        else:
            path = Path(labels)
            self.labels = read_labels_h5(path)
            self.root = Path(root) if root is not None else path.resolve().parent
        self.cache_size = int(cache_size)
        self.load_images = bool(load_images)
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
            if self.load_images or videos:
                names = [c for c in order if c in videos]
            else:
                names = order
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
            self._views[s] = (tuple(names), cols, sub)
            for c in names:
                if c in videos:
                    p = Path(videos[c])
                    self._video_paths[(s, c)] = p if p.is_absolute() else self.root / p
        self._sources: dict[tuple[str, str], FrameSource] = {}
        self._inherited: list[FrameSource] = []
        self._pid = os.getpid()

    def __len__(self) -> int:
        return len(self.labels)

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
                    f"to {self.root}; pass root= to change that)"
                ) from exc
            self._sources[key] = src
        return src

    def __getitem__(self, i: int) -> dict[str, Any]:
        n = len(self)
        if not -n <= int(i) < n:
            raise IndexError(f"sample {i} is outside 0..{n - 1}")
        i = int(i) % n
        lab = self.labels
        s = str(lab.session[i])
        fi = int(lab.frame_index[i])
        names, cols, rig = self._views[s]
        p2 = lab.points2d[i, cols].copy()
        finite2 = np.isfinite(p2).all(-1)
        vis = finite2 if lab.visible2d is None else (lab.visible2d[i, cols] & finite2)
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
        return {
            "session": s,
            "frame_index": fi,
            "index": i,
            "rig": rig,
            "camera_names": names,
            "images": images,
            "points2d": p2,
            "visible2d": vis,
            "points3d": p3,
            "mask3d": np.isfinite(p3).all(-1),
        }

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
