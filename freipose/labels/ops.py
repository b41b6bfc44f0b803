"""Merging, splitting and exporting labels sets.

Video paths in ``labels.h5`` are relative to the file, so every function that writes a
labels set elsewhere rebases them (:func:`rebase_videos`).
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from freipose.errors import FreiPoseError
from freipose.io.atomic import atomic_write_text
from freipose.io.labels import LabelSet, SessionInfo

log = logging.getLogger(__name__)

EXPORT_FORMATS = ("dlc", "anipose", "freipose")


class LabelsOpError(FreiPoseError):
    """A merge/split/export cannot be done; the message says why and how to fix it."""


def rebase_videos(labels: LabelSet, src_dir: str | Path, dst_dir: str | Path) -> LabelSet:
    """Video paths relative to ``src_dir`` -> relative to ``dst_dir`` (absolute stay)."""
    src_dir, dst_dir = Path(src_dir).resolve(), Path(dst_dir).resolve()
    sessions = {}
    for name, info in labels.sessions.items():
        vids = {}
        for cam, p in info.videos.items():
            pp = Path(p)
            vids[cam] = p if pp.is_absolute() else os.path.relpath(src_dir / pp, dst_dir)
        sessions[name] = SessionInfo(info.calibration, vids, info.fps, info.instances)
    return _replace(labels, sessions=sessions)


def _replace(labels: LabelSet, **kw: object) -> LabelSet:
    fields = dict(
        session=labels.session,
        frame_index=labels.frame_index,
        points2d=labels.points2d,
        points3d=labels.points3d,
        cameras=labels.cameras,
        keypoints=labels.keypoints,
        sessions=dict(labels.sessions),
        visible2d=labels.visible2d,
        individual=labels.individual,
    )
    fields.update(kw)
    return LabelSet(**fields)  # type: ignore[arg-type]


def _same_session(a: SessionInfo, b: SessionInfo) -> bool:
    if (a.calibration is None) != (b.calibration is None):
        return False
    if a.calibration is not None and b.calibration is not None:
        if set(a.calibration.names) != set(b.calibration.names):
            return False
        if not all(a.calibration[c].allclose(b.calibration[c]) for c in a.calibration.names):
            return False
    return True


def merge_labels(parts: Sequence[LabelSet], names: Sequence[str] | None = None) -> LabelSet:
    """Concatenate labels sets: union of cameras and keypoints (first-seen order).

    A session present in several inputs must have the same cameras in each; a (session,
    frame, individual) labeled in two inputs is an error (it would count twice in training).
    The result has ``individual`` when an input has (rows of the others: ``""``).

    Raises:
        LabelsOpError: conflicting sessions or duplicate labels (names the inputs).
    """
    if not parts:
        raise LabelsOpError("nothing to merge")
    names = list(names) if names is not None else [f"input {i + 1}" for i in range(len(parts))]
    cams: list[str] = []
    kps: list[str] = []
    for p in parts:
        cams += [c for c in p.cameras if c not in cams]
        kps += [k for k in p.keypoints if k not in kps]
    sessions: dict[str, SessionInfo] = {}
    owner: dict[str, str] = {}
    seen: dict[tuple[str, int], str] = {}
    cols = []
    for p, nm in zip(parts, names):
        for s, info in p.sessions.items():
            if s in sessions:
                if not _same_session(sessions[s], info):
                    raise LabelsOpError(
                        f"session {s!r} has different cameras in {owner[s]} and {nm}; rename "
                        f"one of them before merging"
                    )
                vids = dict(sessions[s].videos)
                vids.update(info.videos)
                prev = sessions[s]
                sessions[s] = SessionInfo(prev.calibration, vids, prev.fps, prev.instances)
            else:
                sessions[s], owner[s] = info, nm
        keys = set()
        inds = p.individual if p.individual is not None else [""] * len(p)
        for s, f, a in zip(p.session, p.frame_index, inds):
            key = (str(s), int(f), str(a))
            if key in seen:
                who = f" animal {key[2]!r}" if key[2] else ""
                raise LabelsOpError(
                    f"session {key[0]!r} frame {key[1]}{who} is labeled in both {seen[key]} "
                    f"and {nm}; remove the duplicate from one input"
                )
            keys.add(key)
        for key in keys:
            seen[key] = nm
        cols.append(([cams.index(c) for c in p.cameras], [kps.index(k) for k in p.keypoints]))
    n = sum(len(p) for p in parts)
    p2 = np.full((n, len(cams), len(kps), 2), np.nan)
    p3 = np.full((n, len(kps), 3), np.nan)
    any_vis = any(p.visible2d is not None for p in parts)
    vis = np.zeros((n, len(cams), len(kps)), dtype=bool)
    r = 0
    for p, (ci, ki) in zip(parts, cols):
        m = len(p)
        p2[np.ix_(range(r, r + m), ci, ki)] = p.points2d
        p3[np.ix_(range(r, r + m), ki)] = p.points3d
        v = p.visible2d if p.visible2d is not None else np.isfinite(p.points2d).all(-1)
        vis[np.ix_(range(r, r + m), ci, ki)] = v
        r += m
    return LabelSet(
        np.concatenate([p.session for p in parts]),
        np.concatenate([p.frame_index for p in parts]),
        p2,
        p3,
        tuple(cams),
        tuple(kps),
        sessions,
        vis if any_vis else None,
        _merged_individuals(parts),
    )


def _merged_individuals(parts: Sequence[LabelSet]) -> np.ndarray | None:
    """The ``individual`` of merged parts (``""`` for parts without), or None if none has."""
    if all(p.individual is None for p in parts):
        return None
    return np.concatenate(
        [p.individual if p.individual is not None else np.full(len(p), "", object) for p in parts]
    )


def split_labels(
    labels: LabelSet,
    eval_fraction: float = 0.3,
    group_pattern: str | None = None,
    eval_groups: Sequence[str] | None = None,
    seed: int = 0,
) -> tuple[LabelSet, LabelSet, list[str]]:
    """Split by session (or by a group of sessions) so no recording is in both parts.

    Groups are sessions, or with ``group_pattern`` (a regex) the first match in the session
    name (e.g. ``^[^_]+`` groups sessions by animal). Eval groups are ``eval_groups`` or a
    seeded random choice whose label count comes closest to ``eval_fraction``.

    Returns:
        ``(train, eval, eval_group_names)``.

    Raises:
        LabelsOpError: fewer than two groups, unknown eval groups, an empty part.
    """
    if not 0 < eval_fraction < 1:
        raise LabelsOpError(f"--eval must be between 0 and 1, got {eval_fraction}")

    def group(s: str) -> str:
        if group_pattern is None:
            return s
        m = re.search(group_pattern, s)
        return m.group(0) if m else s

    groups = np.array([group(str(s)) for s in labels.session], dtype=object)
    names, counts = np.unique(groups, return_counts=True)
    names = [str(x) for x in names]
    if len(names) < 2:
        raise LabelsOpError(
            f"the labels hold one recording group ({names}); a split that never shares a "
            f"recording needs at least two sessions (merge more sessions first)"
        )
    if eval_groups:
        unknown = sorted(set(eval_groups) - set(names))
        if unknown:
            raise LabelsOpError(f"eval groups {unknown} are not in the labels (groups: {names})")
        chosen = list(eval_groups)
    else:
        rng = np.random.default_rng(seed)
        target = eval_fraction * len(labels)
        best, best_cost = None, np.inf
        order = list(range(len(names)))
        for _ in range(200):
            rng.shuffle(order)
            acc, pick = 0, []
            for i in order:
                if (
                    abs(acc + counts[i] - target) <= abs(acc - target)
                    and len(pick) < len(names) - 1
                ):
                    acc += counts[i]
                    pick.append(i)
            if not pick:
                pick = [int(np.argmin(np.abs(counts - target)))]
                acc = counts[pick[0]]
            cost = abs(acc - target)
            if cost < best_cost:
                best, best_cost = sorted(pick), cost
        chosen = [names[i] for i in best or []]
    is_eval = np.isin(groups, chosen)
    if is_eval.all() or not is_eval.any():
        raise LabelsOpError("the split leaves one part empty; choose other eval groups")
    return labels.select(~is_eval), labels.select(is_eval), chosen


def split_by_time(
    labels: LabelSet,
    eval_fraction: float = 0.3,
    gap: int = 50,
    blocks: int = 1,
    seed: int = 0,
) -> tuple[LabelSet, LabelSet, list[str]]:
    """Split every recording into contiguous time blocks, held out with a gap around them.

    Each session's labeled frames, in order, fall into ``blocks`` equal segments; in each,
    a contiguous run of ``eval_fraction`` of the segment's frames (at a seeded random
    place) is held out, with every instant of those frames (all animals of a frame).
    Training instants less than ``gap`` frames from a held-out instant of the same session
    are dropped, so no training frame is a near-copy of a held-out one (neighbouring video
    frames look almost the same).

    Args:
        labels: the labels set (one or more sessions).
        eval_fraction: share of each session's labeled frames held out, in (0, 1).
        gap: frames between a held-out instant and the nearest training instant.
        blocks: held-out blocks per session.
        seed: the blocks' places.

    Returns:
        ``(train, eval, blocks)``: the block descriptions ``session frames A-B``.

    Raises:
        LabelsOpError: bad arguments, or a split that leaves one part empty.
    """
    if not 0 < eval_fraction < 1:
        raise LabelsOpError(f"--eval must be between 0 and 1, got {eval_fraction}")
    if gap < 0 or blocks < 1:
        raise LabelsOpError(f"--gap must be >= 0 and --blocks >= 1, got {gap} and {blocks}")
    rng = np.random.default_rng(seed)
    is_eval = np.zeros(len(labels), bool)
    keep = np.ones(len(labels), bool)
    described = []
    for sess in sorted(set(labels.session)):
        rows = np.flatnonzero(labels.session == sess)
        fi = labels.frame_index[rows]
        frames = np.unique(fi)  # the instants of one frame (several animals) stay together
        for seg in np.array_split(frames, min(blocks, len(frames))):
            size = int(round(eval_fraction * len(seg)))
            if size < 1:
                continue
            start = int(rng.integers(0, len(seg) - size + 1))
            f = seg[start : start + size]
            is_eval[rows[np.isin(fi, f)]] = True
            described.append(f"{sess} frames {int(f.min())}-{int(f.max())}")
        ev_f = fi[is_eval[rows]]
        if len(ev_f):
            near = np.abs(fi[:, None] - ev_f[None, :]).min(1) < gap
            keep[rows] = is_eval[rows] | ~near
    train = ~is_eval & keep
    if not is_eval.any() or not train.any():
        raise LabelsOpError(
            f"the time split leaves {int(train.sum())} training and {int(is_eval.sum())} held-out "
            f"instants; label more frames, or lower --gap ({gap}) or change --eval "
            f"({eval_fraction})"
        )
    return labels.select(train), labels.select(is_eval), described


def _session_dir(out: Path, session: str) -> Path:
    safe = re.sub(r"[^\w.\-]+", "_", session)
    return out / safe


def _check_empty_dir(out: Path) -> None:
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise LabelsOpError(f"{out}: the export folder must be new or empty")


def export_labels(
    labels: LabelSet, out: str | Path, fmt: str, labels_dir: str | Path, scorer: str = "freipose"
) -> list[Path]:
    """Write labels in another tool's format into folder ``out``.

    The folder is written atomically: it appears complete or not at all.

    * ``dlc``: ``labeled-data/<session>_<camera>/CollectedData_<scorer>.csv`` (+ ``.h5``
      with PyTables), rows ``labeled-data/<folder>/img<frame:05d>.png``; the frames (all
      labeled frames of the session, in every camera folder) are extracted from the session
      videos when they are available. Labels with ``individual``: multi-animal tables
      (``scorer / individuals / bodyparts / coords``).
    * ``anipose``: ``<session>/pose-2d/<session>_<camera>.csv`` (one row per video frame up
      to the last labeled one, likelihood 1 for labels) + ``<session>/calibration.toml``.
    * ``freipose``: ``<session>/anno.json`` (the original format, xyz in metres) +
      ``<session>/M.json``.

    Returns:
        The written files (paths inside ``out``).
    """
    from freipose.io.calibration import save_calibration

    if fmt not in EXPORT_FORMATS:
        raise LabelsOpError(f"unknown export format {fmt!r}; use one of {list(EXPORT_FORMATS)}")
    out = Path(out)
    _check_empty_dir(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    written: list[Path] = []
    try:
        for sess in sorted(set(labels.session)):
            sel = labels.session == sess
            info = labels.sessions[sess]
            rig = info.calibration
            cams = list(rig.names) if rig is not None else list(labels.cameras)
            cols = [labels.cameras.index(c) for c in cams]
            fi = labels.frame_index[sel]
            p2 = labels.points2d[sel][:, cols]
            animals = None
            if fmt == "dlc" and labels.individual is not None:
                animals, fi, p2 = _by_animal(labels.individual[sel], fi, p2, sess)
            if len(set(fi.tolist())) != len(fi):
                raise LabelsOpError(
                    f"session {sess!r} has several labels per frame (several animals); "
                    f"{fmt} export supports one animal per frame (dlc: several with names)"
                )
            if fmt == "dlc":
                written += _export_dlc(tmp, sess, cams, fi, p2, labels, info, labels_dir,
                                       scorer, animals)  # fmt: skip
            elif fmt == "anipose":
                written += _export_anipose(tmp, sess, cams, fi, p2, labels.keypoints, scorer)
                if rig is not None:
                    d = _session_dir(tmp, sess)
                    save_calibration(rig, d / "calibration.toml", "anipose")
                    written.append(d / "calibration.toml")
            else:
                d = _session_dir(tmp, sess)
                d.mkdir(parents=True, exist_ok=True)
                anno = {}
                p3 = labels.points3d[sel]
                for i, f in enumerate(fi):
                    e: dict[str, object] = {}
                    for j, c in enumerate(cams):
                        uv = p2[i, j]
                        ok = np.isfinite(uv).all(-1)
                        e[c] = {
                            "kp_uv": np.where(ok[:, None], uv, 0.0).tolist(),
                            "vis": ok.astype(float).tolist(),
                        }
                    ok3 = np.isfinite(p3[i]).all(-1)
                    e["xyz"] = (np.where(ok3[:, None], p3[i], 0.0) / 1000.0).tolist()
                    e["vis3d"] = ok3.astype(float).tolist()
                    anno[f"{int(f):08d}.png"] = e
                atomic_write_text(d / "anno.json", json.dumps(anno))
                written.append(d / "anno.json")
                if rig is not None:
                    save_calibration(rig, d / "M.json", "mjson")
                    written.append(d / "M.json")
        if out.exists():
            out.rmdir()
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return [out / p.relative_to(tmp) for p in written]


def _export_dlc(
    tmp: Path,
    sess: str,
    cams: list[str],
    fi: np.ndarray,
    p2: np.ndarray,
    labels: LabelSet,
    info: SessionInfo,
    labels_dir: str | Path,
    scorer: str,
    animals: Sequence[str] | None = None,
) -> list[Path]:
    """One camera folder per camera; ``animals``: p2 is (F, C, A, K, 2), a multi-animal table."""
    import cv2

    from freipose.io.video import FrameSource
    from freipose.labels.dlc import write_dlc_table

    written = []
    for j, cam in enumerate(cams):
        folder = re.sub(r"[^\w.\-]+", "_", f"{sess}_{cam}")
        d = tmp / "labeled-data" / folder
        d.mkdir(parents=True, exist_ok=True)
        keep = np.isfinite(p2[:, j]).all(-1).reshape(len(fi), -1).any(-1)
        index = [f"labeled-data/{folder}/img{int(f):05d}.png" for f in fi[keep]]
        written += write_dlc_table(
            d / f"CollectedData_{scorer}.csv", scorer, labels.keypoints, index, p2[keep, j],
            individuals=animals,
        )  # fmt: skip
        video = info.videos.get(cam)
        if video is not None:
            vp = Path(video) if Path(video).is_absolute() else Path(labels_dir) / video
            if vp.exists():
                # every labeled frame of the session, also those this camera has no label
                # in: all folders then hold the same images, so they can serve as the
                # cameras' frame sources when the export is imported without the videos
                with FrameSource(vp) as src:
                    for f in fi:
                        img_path = d / f"img{int(f):05d}.png"
                        cv2.imwrite(str(img_path), src.read(int(f)))
                        written.append(img_path)
    return written


def _by_animal(
    individual: np.ndarray, fi: np.ndarray, p2: np.ndarray, sess: str
) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Rows of (frame, animal) as frames with an animal axis.

    Args:
        individual: (N,) each row's animal.
        fi: (N,) each row's frame.
        p2: (N, C, K, 2) points.
        sess: the session (for messages).

    Returns:
        ``(animals (A,), frames (F,), points (F, C, A, K, 2))``.

    Raises:
        LabelsOpError: a row without an animal's name, or an animal twice in a frame.
    """
    names = list(dict.fromkeys(str(a) for a in individual))
    if "" in names:
        raise LabelsOpError(
            f"session {sess!r} mixes rows with and without an animal's name (individual); "
            f"name every row's animal to export several animals"
        )
    frames = np.unique(fi)
    out = np.full((len(frames), p2.shape[1], len(names), *p2.shape[2:]), np.nan)
    seen = set()
    for r, (f, a) in enumerate(zip(fi, individual)):
        key = (int(f), str(a))
        if key in seen:
            raise LabelsOpError(f"session {sess!r} frame {key[0]}: animal {key[1]!r} twice")
        seen.add(key)
        out[np.searchsorted(frames, f), :, names.index(str(a))] = p2[r]
    return names, frames, out


def _export_anipose(
    tmp: Path,
    sess: str,
    cams: list[str],
    fi: np.ndarray,
    p2: np.ndarray,
    keypoints: Sequence[str],
    scorer: str,
) -> list[Path]:
    from freipose.labels.dlc import write_dlc_table

    d = _session_dir(tmp, sess) / "pose-2d"
    d.mkdir(parents=True, exist_ok=True)
    n = int(fi.max()) + 1 if len(fi) else 0
    written = []
    for j, cam in enumerate(cams):
        pts = np.full((n, len(keypoints), 2), np.nan)
        pts[fi] = p2[:, j]
        lik = np.where(np.isfinite(pts).all(-1), 1.0, 0.0)
        name = re.sub(r"[^\w.\-]+", "_", f"{sess}_{cam}")
        written += write_dlc_table(
            d / f"{name}.csv", scorer, keypoints, [str(i) for i in range(n)], pts, lik
        )
    return written
