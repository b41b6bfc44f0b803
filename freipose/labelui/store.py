"""The labels being edited: one state per instant, saved to ``labels.h5`` after every edit.

Each instant (a session, a video frame and, with several animals, one of them) has labels
``points`` (V, K, 2) and states
``status`` (V, K) over the session's V cameras (see :mod:`freipose.labelui.geometry`),
and a version number that every save increments: a save that names an older version is
refused (:class:`StaleVersionError`), so two tabs editing one instant never overwrite
each other silently.

``labels.h5`` holds the instants with at least one label, in the format of
:mod:`freipose.io.labels` (``points2d`` and ``visible2d`` from the visible labels,
``points3d`` triangulated from them) plus the group ``labelui`` with the dataset
``status`` (N, V, K) int8, so that occluded and not-in-view marks survive a restart.
Rows of sessions that this run does not edit are kept unchanged. With several animals the
file has the ``individual`` column: one row per animal labeled at a frame.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from freipose.io.atomic import atomic_h5
from freipose.io.labels import LabelSet, SessionInfo, fill_labels_h5
from freipose.io.poses import PoseData
from freipose.io.session import Session
from freipose.labelui.geometry import (
    STATE_NAMES,
    UNLABELED,
    VISIBLE,
    InstantGeometry,
    bone_lengths,
    bone_report,
    instant_geometry,
    median_lengths,
)
from freipose.skeleton import Skeleton

STATUS_DATASET = "labelui/status"
ANIMALS_ATTR = "animals"  # attribute of the labelui group: the animals the run labels


@dataclass(frozen=True)
class Instant:
    """One time instant to label (with several animals: one animal at one instant).

    Attributes:
        session: the session's name.
        frame: the video frame number.
        confidence: mean keypoint confidence of the prediction (NaN when unknown).
        individual: the animal's name; ``""`` when the run labels one animal.
    """

    session: str
    frame: int
    confidence: float = float("nan")
    individual: str = ""

    @property
    def key(self) -> tuple[str, int, str]:
        """(session, frame, individual): what identifies the instant."""
        return self.session, self.frame, self.individual


@dataclass(frozen=True)
class StoreSettings:
    """Thresholds of the live feedback.

    Attributes:
        max_residual: reprojection residual (px) above which a label is highlighted.
        bone_tolerance: relative deviation from the median limb length that is flagged.
    """

    max_residual: float = 3.0
    bone_tolerance: float = 0.3


class StaleVersionError(Exception):
    """A save named an older version of the instant than the stored one.

    Attributes:
        current: the instant's stored state (JSON-ready), for the client to reload.
    """

    def __init__(self, current: dict[str, object]):
        super().__init__("the instant was changed elsewhere")
        self.current = current


def _rounded(a: np.ndarray, digits: int = 3) -> list[float] | None:
    return None if not np.all(np.isfinite(a)) else [round(float(v), digits) for v in a]


class LabelStore:
    """Label states of the instants of a labeling run, written to ``output`` on each save.

    Args:
        sessions: the sessions being labeled.
        skeleton: the keypoints (K) and limbs.
        instants: the instants, in labeling order.
        output: the labels file.
        existing: labels read from ``output`` (resumed; rows of other sessions kept).
        existing_status: (N, V, K) states stored with ``existing`` (None: from the labels).
        predictions: session name -> its predicted poses (pre-filled, unconfirmed).
        settings: feedback thresholds.

    Attributes:
        saves: the edits saved since the store was opened.
    """

    def __init__(
        self,
        sessions: Sequence[Session],
        skeleton: Skeleton,
        instants: Sequence[Instant],
        output: Path,
        existing: LabelSet | None = None,
        existing_status: np.ndarray | None = None,
        predictions: Mapping[str, PoseData] | None = None,
        settings: StoreSettings | None = None,
    ):
        self.sessions = {s.name: s for s in sessions}
        self.skeleton = skeleton
        self.output = Path(output)
        self.settings = settings or StoreSettings()
        self.predictions = dict(predictions or {})
        cams: list[str] = []
        for s in sessions:
            cams += [c for c in s.cameras if c not in cams]
        self.cameras = tuple(cams)
        self._lock = threading.Lock()
        self._keep = self._foreign_rows(existing)
        self.instants: list[Instant] = list(instants)
        self._index = {x.key: i for i, x in enumerate(self.instants)}
        self._points: list[np.ndarray] = []
        self._status: list[np.ndarray] = []
        for x in self.instants:
            v = len(self.sessions[x.session].cameras)
            self._points.append(np.full((v, skeleton.num_keypoints, 2), np.nan))
            self._status.append(np.zeros((v, skeleton.num_keypoints), np.int8))
        self._version = [0] * len(self.instants)
        self.saves = 0
        if existing is not None:
            self._resume(existing, existing_status)
        # the instants of each (session, frame): the animals of one moment
        self._moments: dict[tuple[str, int], list[int]] = {}
        for i, x in enumerate(self.instants):
            self._moments.setdefault((x.session, x.frame), []).append(i)
        K, L = skeleton.num_keypoints, len(skeleton.limbs)
        self._p3d = np.full((len(self.instants), K, 3), np.nan)
        self._bones = np.full((len(self.instants), L), np.nan)
        self._geometry: list[InstantGeometry | None] = [None] * len(self.instants)
        for i in range(len(self.instants)):
            self._update_3d(i)

    # -- set-up ---------------------------------------------------------------------------
    def _foreign_rows(self, existing: LabelSet | None) -> LabelSet | None:
        if existing is None:
            return None
        other = np.array([s not in self.sessions for s in existing.session], bool)
        return existing.select(other) if other.any() else None

    def _resume(self, existing: LabelSet, status: np.ndarray | None) -> None:
        """Take the labels of this run's sessions from ``existing`` (new instants appended)."""
        for r in range(len(existing)):
            name, frame = str(existing.session[r]), int(existing.frame_index[r])
            if name not in self.sessions:
                continue
            ind = "" if existing.individual is None else str(existing.individual[r])
            key = (name, frame, ind)
            if key not in self._index:
                self._index[key] = len(self.instants)
                self.instants.append(Instant(name, frame, individual=ind))
                v = len(self.sessions[name].cameras)
                self._points.append(np.full((v, self.skeleton.num_keypoints, 2), np.nan))
                self._status.append(np.zeros((v, self.skeleton.num_keypoints), np.int8))
                self._version.append(0)
            i = self._index[key]
            for v, cam in enumerate(self.sessions[name].cameras):
                if cam not in existing.cameras:
                    continue
                c = existing.cameras.index(cam)
                pts = existing.points2d[r, c]
                ok = np.isfinite(pts).all(-1)
                if existing.visible2d is not None:
                    ok &= existing.visible2d[r, c]
                st = np.where(ok, VISIBLE, UNLABELED).astype(np.int8)
                if status is not None:
                    st = np.where(ok, VISIBLE, np.where(status[r, c] > VISIBLE, status[r, c], 0))
                self._points[i][v] = np.where(ok[:, None], pts, np.nan)
                self._status[i][v] = st.astype(np.int8)

    # -- queries --------------------------------------------------------------------------
    @property
    def animals(self) -> tuple[str, ...]:
        """The animals labeled at each instant (``()`` for one animal)."""
        return tuple(dict.fromkeys(x.individual for x in self.instants if x.individual))

    def __len__(self) -> int:
        return len(self.instants)

    def session(self, i: int) -> Session:
        """The session of instant ``i``."""
        return self.sessions[self.instants[i].session]

    def _update_3d(self, i: int, changed: np.ndarray | None = None) -> None:
        """Recompute the geometry of instant ``i`` (only the ``changed`` (K,) keypoints)."""
        prev = self._geometry[i] if changed is not None else None
        geo = instant_geometry(self._points[i], self._status[i], self.session(i).rig, prev, changed)
        self._geometry[i] = geo
        self._p3d[i] = geo.points3d
        self._bones[i] = bone_lengths(self.skeleton, geo.points3d)

    def _labels_json(self, i: int) -> dict[str, dict[str, dict[str, object]]]:
        out: dict[str, dict[str, dict[str, object]]] = {}
        kps = self.skeleton.keypoints
        for v, cam in enumerate(self.session(i).cameras):
            d: dict[str, dict[str, object]] = {}
            for k, kp in enumerate(kps):
                st = int(self._status[i][v, k])
                if st == UNLABELED:
                    continue
                entry: dict[str, object] = {"state": STATE_NAMES[st]}
                if st == VISIBLE:
                    entry["x"], entry["y"] = (round(float(c), 3) for c in self._points[i][v, k])
                d[kp] = entry
            out[cam] = d
        return out

    def _per_view(self, i: int, a: np.ndarray, digits: int = 3) -> dict[str, dict[str, object]]:
        """(V, K, ...) values as camera -> keypoint -> value, finite entries only."""
        out: dict[str, dict[str, object]] = {}
        for v, cam in enumerate(self.session(i).cameras):
            d: dict[str, object] = {}
            for k, kp in enumerate(self.skeleton.keypoints):
                val = np.atleast_1d(a[v, k])
                if np.all(np.isfinite(val)):
                    vals = [round(float(x), digits) for x in val]
                    d[kp] = vals if len(vals) > 1 else vals[0]
            out[cam] = d
        return out

    def _predicted(self, i: int) -> np.ndarray | None:
        x = self.instants[i]
        row = prediction_at(self.predictions.get(x.session), x.frame, x.individual)
        if row is None or row[0].ndim != 2 or not np.isfinite(row[0]).any():
            return None  # not predicted, or several animals and none named
        return self.session(i).rig.project(row[0], distort=True)  # (V, K, 2)

    def state(self, i: int) -> dict[str, object]:
        """Instant ``i`` as the API returns it (labels, predictions, geometry, bones)."""
        with self._lock:
            return self._state(i)

    def _state(self, i: int) -> dict[str, object]:
        x = self.instants[i]
        sess = self.session(i)
        geo = self._geometry[i]
        if geo is None:
            self._update_3d(i)
            geo = self._geometry[i]
        if geo is None:
            raise RuntimeError("the instant's geometry was not computed")
        pred = self._predicted(i)
        ref = median_lengths(np.delete(self._bones, i, axis=0))
        same = self._moments[(x.session, x.frame)]
        labeled = self._labeled()
        return {
            "index": i,
            "session": x.session,
            "frame": x.frame,
            "individual": x.individual,
            "animals": [
                {"index": j, "name": self.instants[j].individual, "labeled": bool(labeled[j])}
                for j in same
            ],
            "others": {
                self.instants[j].individual: self._per_view(
                    j, np.where((self._status[j] == VISIBLE)[..., None], self._points[j], np.nan)
                )
                for j in same
                if j != i and labeled[j]
            },
            "version": self._version[i],
            "cameras": list(sess.cameras),
            "labels": self._labels_json(i),
            "predicted": {} if pred is None else self._per_view(i, pred),
            "points3d": {
                kp: _rounded(geo.points3d[k])
                for k, kp in enumerate(self.skeleton.keypoints)
                if np.all(np.isfinite(geo.points3d[k]))
            },
            "projected": self._per_view(i, geo.projected),
            "residuals": self._per_view(i, geo.residuals),
            "bones": bone_report(self.skeleton, self._bones[i], ref, self.settings.bone_tolerance),
            "progress": self._progress(labeled),
        }

    def _labeled(self) -> np.ndarray:
        return np.array([bool((s != UNLABELED).any()) for s in self._status], bool)

    def _progress(self, done: np.ndarray | None = None) -> dict[str, object]:
        """Labeled instants / total, per keypoint (``done``: :meth:`_labeled`, if known)."""
        done = self._labeled() if done is None else done
        per_kp = np.zeros(self.skeleton.num_keypoints, np.int64)
        for s in self._status:
            per_kp += (s != UNLABELED).any(0)
        return {
            "labeled": int(done.sum()),
            "total": len(self.instants),
            "done": done.tolist(),
            "per_keypoint": per_kp.tolist(),
            "triangulated": np.isfinite(self._p3d).all(-1).sum(0).tolist(),
        }

    def done(self) -> list[bool]:
        """Per instant: whether it has at least one label."""
        with self._lock:
            return self._labeled().tolist()

    def progress(self) -> dict[str, object]:
        """Labeled instants / total, per keypoint (labeled anywhere, triangulated)."""
        with self._lock:
            return self._progress()

    # -- edits ----------------------------------------------------------------------------
    def save(
        self, i: int, version: int, points: np.ndarray, status: np.ndarray
    ) -> dict[str, object]:
        """Replace the labels of instant ``i`` and write the labels file.

        Args:
            i: the instant.
            version: the version the edit was made on.
            points: (V, K, 2) label pixels (NaN where not visible).
            status: (V, K) label states.

        Returns:
            The instant's new state (its version incremented).

        Raises:
            StaleVersionError: ``version`` is not the stored version.
        """
        with self._lock:
            if version != self._version[i]:
                raise StaleVersionError(self._state(i))
            old = (self._points[i], self._status[i], self._geometry[i])
            new_points = np.where((status == VISIBLE)[..., None], points, np.nan)
            same = np.all((new_points == old[0]) | (np.isnan(new_points) & np.isnan(old[0])), -1)
            changed = ~(same & (status == old[1])).all(0)  # (K,)
            self._points[i], self._status[i] = new_points, status.astype(np.int8)
            self._update_3d(i, changed)
            try:
                self._write()
            except BaseException:  # nothing changed unless the file was written
                self._points[i], self._status[i], self._geometry[i] = old
                self._update_3d(i, changed)
                raise
            self._version[i] += 1
            self.saves += 1
            return self._state(i)

    # -- output ---------------------------------------------------------------------------
    def label_set(self) -> tuple[LabelSet, np.ndarray]:
        """The labels file's content: the labeled instants (and kept rows) and their states."""
        with self._lock:
            return self._label_set()

    def _label_set(self) -> tuple[LabelSet, np.ndarray]:
        keep = self._keep
        cams = list(self.cameras)
        if keep is not None:
            cams += [c for c in keep.cameras if c not in cams]
        K = self.skeleton.num_keypoints
        rows = [int(i) for i in np.flatnonzero(self._labeled())]
        n0 = 0 if keep is None else len(keep)
        n = n0 + len(rows)
        p2 = np.full((n, len(cams), K, 2), np.nan)
        p3 = np.full((n, K, 3), np.nan)
        vis = np.zeros((n, len(cams), K), bool)
        status = np.zeros((n, len(cams), K), np.int8)
        sess: list[str] = []
        frames: list[int] = []
        animals: list[str] = []
        infos: dict[str, SessionInfo] = {}
        if keep is not None:
            cols = [cams.index(c) for c in keep.cameras]
            p2[:n0, cols] = keep.points2d
            p3[:n0] = keep.points3d
            kv = np.isfinite(keep.points2d).all(-1) if keep.visible2d is None else keep.visible2d
            vis[:n0, cols] = kv
            status[:n0, cols] = np.where(kv, VISIBLE, UNLABELED)
            sess += [str(s) for s in keep.session]
            frames += [int(f) for f in keep.frame_index]
            animals += [""] * n0 if keep.individual is None else [str(a) for a in keep.individual]
            infos.update(keep.sessions)
        for r, i in enumerate(rows, start=n0):
            x = self.instants[i]
            cols = [cams.index(c) for c in self.session(i).cameras]
            p2[r, cols] = self._points[i]
            vis[r, cols] = self._status[i] == VISIBLE
            status[r, cols] = self._status[i]
            p3[r] = self._p3d[i]
            sess.append(x.session)
            frames.append(x.frame)
            animals.append(x.individual)
        for name in {self.instants[i].session for i in rows}:
            infos[name] = self._session_info(self.sessions[name])
        # the individual column only where some row names an animal: a one-animal run
        # writes the file exactly as before
        ind = np.array(animals, dtype=object) if any(animals) else None
        ls = LabelSet(np.array(sess, dtype=object), np.array(frames, np.int64), p2, p3,
                      tuple(cams), self.skeleton.keypoints, infos, vis, ind)  # fmt: skip
        return ls, status

    def _session_info(self, s: Session) -> SessionInfo:
        base = self.output.resolve().parent
        videos = {c: os.path.relpath(Path(p).resolve(), base) for c, p in s.videos.items()}
        fps = s.fps if np.isfinite(s.fps) else None
        return SessionInfo(s.rig, videos, fps)

    def _write(self) -> None:
        labels, status = self._label_set()
        with atomic_h5(self.output.resolve()) as f:
            fill_labels_h5(f, labels)
            f.create_dataset(STATUS_DATASET, data=status, compression="gzip")
            if self.animals:
                f["labelui"].attrs[ANIMALS_ATTR] = list(self.animals)

    def write(self) -> None:
        """Write the labels file now (atomically; a symbolic link is written through).

        The caller holds the file's :func:`~freipose.io.labels.labels_file_lock` (the
        server does, while it runs).
        """
        with self._lock:
            self._write()


def prediction_at(
    pred: PoseData | None, frame: int, individual: str = ""
) -> tuple[np.ndarray, np.ndarray] | None:
    """The prediction of one instant: ``(poses, confidence)`` at ``frame``.

    Args:
        pred: a session's predictions (None: none).
        frame: the video frame.
        individual: the animal, for predictions with an animal axis (``""``: every animal).

    Returns:
        (K, 3) float64 poses and (K,) confidences, or (A, K, 3) and (A, K) for every animal
        of predictions with an animal axis when ``individual`` is ``""``; None where the
        frame (or the named animal) was not predicted.
    """
    if pred is None:
        return None
    hit = np.flatnonzero(pred.frame_index == frame)
    if not len(hit):
        return None
    poses = np.asarray(pred.poses[hit[0]], dtype=np.float64)
    conf = np.asarray(pred.confidence[hit[0]])
    if pred.individuals is not None and individual:
        if individual not in pred.individuals:
            return None
        a = pred.individuals.index(individual)
        poses, conf = poses[a], conf[a]
    return poses, conf


def read_animals(path: Path) -> tuple[str, ...]:
    """The animals a labeling run of this file labeled (``()``: not recorded, or one)."""
    with h5py.File(path, "r") as f:
        grp = f.get("labelui")
        names = [] if grp is None else list(grp.attrs.get(ANIMALS_ATTR, []))
    return tuple(n.decode() if isinstance(n, bytes) else str(n) for n in names)


def read_status(path: Path, shape: tuple[int, ...]) -> np.ndarray | None:
    """The stored label states of a labels file (N, V, K), or None if absent or mis-shaped."""
    with h5py.File(path, "r") as f:
        if STATUS_DATASET not in f:
            return None
        st = np.asarray(f[STATUS_DATASET][()], np.int8)
    return st if st.shape == shape else None
