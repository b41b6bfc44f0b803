"""Per-camera label files as other tools write them: SLEAP predictions and DeepLabCut tables.

``label_files = ["sleap"]`` writes ``OUTDIR/<camera>/<camera>.slp`` (sleap-anipose's layout:
one folder per camera), each holding one SLEAP *predicted* instance per frame with a score
per point; ``"dlc"`` writes ``OUTDIR/labeled-data/<session>_<camera>/CollectedData_synthetic.csv``
(a DeepLabCut project's labeled-data table, the folder named after the session and camera:
scorer / bodyparts / coords header rows, one row per frame ``img<frame>.png``, x and y per
keypoint).
``"sleap-session"`` writes ``OUTDIR/<session>.slp``: one SLEAP multi-camera file as SLEAP's
multi-view labeling writes it, with a recording session (the true cameras, a video per
camera) and per frame an instance group per animal joining its instances across the views.
Several animals (``individuals``): a SLEAP file holds one track per animal (named after it)
and one predicted instance per animal and frame; the DeepLabCut tables have the
multi-animal header ``scorer / individuals / bodyparts / coords`` and the session folder a
multi-animal project's ``config.yaml`` (``multianimalproject: true``, ``individuals``,
``multianimalbodyparts``).
Only the points visible in that camera are given (the others are missing: NaN, or empty
cells); each is the exact projection plus Gaussian noise of ``label_noise_px``. The point
score falls with the point's noise: ``exp(-e² / (2 (2 s)²))`` times a factor in 0.85..1
(``e`` the point's error, ``s`` the noise level, at least 0.5 px).
"""

from __future__ import annotations

import csv
import io
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from freipose.io.atomic import atomic_write_text
from freipose.synth.errors import SynthError


@dataclass(frozen=True, eq=False)
class NoisyLabels:
    """The label files' 2D points of every frame and camera.

    Attributes:
        points: (T, C, K, 2) noisy points, px; NaN where the keypoint is not visible.
        scores: (T, C, K) per-point scores in (0, 1]; NaN where not visible.
    """

    points: np.ndarray
    scores: np.ndarray


def noisy_labels(
    points2d: np.ndarray, visible: np.ndarray, noise_px: float, rng: np.random.Generator
) -> NoisyLabels:
    """Noisy, scored copies of the visible exact projections.

    Args:
        points2d: (T, C, K, 2) exact projections, px.
        visible: (T, C, K) visibility.
        noise_px: standard deviation of the noise per coordinate, px.
        rng: the random generator.

    Returns:
        :class:`NoisyLabels`.
    """
    err = rng.normal(0.0, noise_px, size=points2d.shape)
    pts = np.where(visible[..., None], points2d + err, np.nan)
    s = max(float(noise_px), 0.5)
    e2 = np.sum(err * err, axis=-1)
    score = np.exp(-e2 / (2 * (2 * s) ** 2)) * rng.uniform(0.85, 1.0, size=e2.shape)
    return NoisyLabels(pts, np.where(visible, score, np.nan))


def _sleap_io() -> Any:
    """The ``sleap_io`` module.

    Raises:
        SynthError: sleap-io is not installed (the message names the extra).
    """
    try:
        import sleap_io
    except ImportError:
        raise SynthError(
            "label_files = sleap needs sleap-io, which is not installed: install the sleap "
            "extra with pip install 'freipose[sleap]' (or leave sleap out of --label-files)"
        ) from None
    return sleap_io


def check_label_formats(formats: Sequence[str]) -> None:
    """Check that the packages the label files of ``formats`` need are installed.

    Called before anything is written, so that a missing extra leaves no half session.

    Raises:
        SynthError: a format needs a package that is not installed.
    """
    if "sleap" in formats or "sleap-session" in formats:
        _sleap_io()


def _instances(
    sio: Any, skeleton: Any, points: np.ndarray, scores: np.ndarray, tracks: Sequence[Any]
) -> dict[int, Any]:
    """SLEAP predicted instances of the animals seen in one view at one instant.

    Args:
        sio: the ``sleap_io`` module.
        skeleton: the SLEAP skeleton.
        points: (A, K, 2) points, NaN where missing.
        scores: (A, K) point scores.
        tracks: (A,) the animals' tracks, or empty (one animal without a track).

    Returns:
        Animal index -> its instance, for the animals with a visible point.
    """
    out = {}
    for a in range(len(points)):
        seen = np.isfinite(points[a, :, 0])
        if seen.any():
            sc = np.where(seen, scores[a], 0.0)
            out[a] = sio.PredictedInstance.from_numpy(
                points[a], skeleton, point_scores=sc, score=float(np.mean(sc[seen])),
                track=tracks[a] if tracks else None,
            )  # fmt: skip
    return out


def _save_slp(sio: Any, labels: Any, path: Path) -> Path:
    """Save SLEAP labels to ``path`` through a temporary name."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    sio.save_slp(labels, str(tmp), verbose=False)
    tmp.replace(path)
    return path


def write_sleap(
    path: Path,
    video: Path,
    keypoints: Sequence[str],
    points: np.ndarray,
    scores: np.ndarray,
    individuals: Sequence[str] | None = None,
) -> Path:
    """Write one camera's predictions as a SLEAP ``.slp`` file.

    Args:
        path: the ``.slp`` file.
        video: the camera's video (stored as the labels' video, relative to the file).
        keypoints: (K,) node names.
        points: (T, K, 2) points, NaN where missing; (T, A, K, 2) with ``individuals``.
        scores: (T, K) point scores, NaN where missing; (T, A, K) with ``individuals``.
        individuals: (A,) the animals: one track each (None: one animal, no track).

    Returns:
        ``path``.

    Raises:
        SynthError: sleap-io is not installed.
    """
    sio = _sleap_io()
    skeleton = sio.Skeleton([sio.Node(k) for k in keypoints], name="rat")
    rel = os.path.relpath(video.resolve(), path.parent.resolve())  # portable with the folder
    vid = sio.Video(filename=Path(rel).as_posix(), open_backend=False)
    tracks = [sio.Track(name=str(n)) for n in individuals] if individuals is not None else []
    if individuals is None:
        points, scores = points[:, None], scores[:, None]
    frames = []
    for t in range(len(points)):
        instances = list(_instances(sio, skeleton, points[t], scores[t], tracks).values())
        if instances:
            frames.append(sio.LabeledFrame(video=vid, frame_idx=t, instances=instances))
    labels = sio.Labels(labeled_frames=frames, videos=[vid], skeletons=[skeleton], tracks=tracks)
    return _save_slp(sio, labels, path)


def write_sleap_session(
    path: Path,
    rig: Any,
    videos: dict[str, Path],
    keypoints: Sequence[str],
    points: np.ndarray,
    scores: np.ndarray,
    individuals: Sequence[str] | None = None,
) -> Path:
    """Write every camera's predictions as one SLEAP multi-camera ``.slp`` file.

    Args:
        path: the ``.slp`` file.
        rig: the cameras (``freipose.geometry.CameraRig``), stored as the session's.
        videos: camera name -> its video (stored relative to the file), in ``rig`` order.
        keypoints: (K,) node names.
        points: (T, C, A, K, 2) points, NaN where missing.
        scores: (T, C, A, K) point scores.
        individuals: (A,) the animals (a track each); None: one animal without a track.

    Returns:
        ``path``.

    Raises:
        SynthError: sleap-io is not installed.
    """
    sio = _sleap_io()
    from sleap_io.model.camera import (
        Camera,
        CameraGroup,
        FrameGroup,
        InstanceGroup,
        RecordingSession,
    )

    skeleton = sio.Skeleton([sio.Node(k) for k in keypoints], name="rat")
    tracks = [sio.Track(name=str(n)) for n in individuals] if individuals is not None else []
    vids, cams = {}, {}
    for c in rig:
        rel = os.path.relpath(videos[c.name].resolve(), path.parent.resolve())
        vids[c.name] = sio.Video(filename=Path(rel).as_posix(), open_backend=False)
        cams[c.name] = Camera(matrix=c.K, dist=c.dist, size=tuple(c.size), rvec=c.rvec,
                              tvec=c.t, name=c.name)  # fmt: skip
    frames, groups = [], {}
    for t in range(len(points)):
        by_animal: list[dict[Any, Any]] = [{} for _ in range(points.shape[2])]
        by_camera = {}
        for ci, name in enumerate(cams):
            seen = _instances(sio, skeleton, points[t, ci], scores[t, ci], tracks)
            for a, inst in seen.items():
                by_animal[a][cams[name]] = inst
            if seen:
                lf = sio.LabeledFrame(video=vids[name], frame_idx=t, instances=list(seen.values()))
                frames.append(lf)
                by_camera[cams[name]] = lf
        igs = [InstanceGroup(instance_by_camera=d) for d in by_animal if d]
        if igs:
            groups[t] = FrameGroup(frame_idx=t, instance_groups=igs,
                                   labeled_frame_by_camera=by_camera)  # fmt: skip
    session = RecordingSession(
        camera_group=CameraGroup(cameras=list(cams.values())),
        video_by_camera={cams[c]: vids[c] for c in cams},
        camera_by_video={vids[c]: cams[c] for c in cams},
        frame_group_by_frame_idx=groups,
    )
    labels = sio.Labels(labeled_frames=frames, videos=list(vids.values()), skeletons=[skeleton],
                        tracks=tracks, sessions=[session])  # fmt: skip
    return _save_slp(sio, labels, path)


def write_dlc(
    path: Path,
    keypoints: Sequence[str],
    points: np.ndarray,
    individuals: Sequence[str] | None = None,
) -> Path:
    """Write one camera's points as a DeepLabCut ``CollectedData_<scorer>.csv`` table.

    Args:
        path: the ``.csv`` file in its labeled-data folder (which names the row index).
        keypoints: (K,) body part names.
        points: (T, K, 2) points, NaN where missing (empty cells); (T, A, K, 2) with
            ``individuals``.
        individuals: (A,) the animals: the multi-animal header's ``individuals`` row.

    Returns:
        ``path``.
    """
    if individuals is None:
        points, names = points[:, None], [""]
    else:
        names = [str(n) for n in individuals]
    cols = [(n, k) for n in names for k in keypoints]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["scorer"] + ["synthetic"] * (2 * len(cols)))
    if individuals is not None:
        w.writerow(["individuals"] + [n for n, _ in cols for _ in (0, 1)])
    w.writerow(["bodyparts"] + [k for _, k in cols for _ in (0, 1)])
    w.writerow(["coords"] + ["x", "y"] * len(cols))
    for t in range(len(points)):
        if not np.isfinite(points[t, ..., 0]).any():
            continue
        cells = ["" if not np.isfinite(v) else f"{v:.3f}" for v in points[t].ravel()]
        w.writerow([f"labeled-data/{path.parent.name}/img{t:05d}.png"] + cells)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, buf.getvalue())
    return path


def write_dlc_config(
    folder: Path, keypoints: Sequence[str], individuals: Sequence[str], videos: dict[str, Path]
) -> Path:
    """Write a multi-animal DeepLabCut project's ``config.yaml`` into ``folder``.

    Args:
        folder: the project (session) folder.
        keypoints: (K,) the body parts (every animal has them all).
        individuals: (A,) the animals.
        videos: camera -> video, listed as the project's ``video_sets``.

    Returns:
        The file.
    """

    def q(v: object) -> str:  # a quoted YAML scalar (JSON strings are YAML)
        return json.dumps(str(v))

    lines = [
        "Task: synthetic",
        "scorer: synthetic",
        "date: synthetic",
        "multianimalproject: true",
        "identity: true",
        f"project_path: {q(folder.resolve())}",
        "video_sets:",
        *[f"  {q(v.resolve())}:\n    crop: 0, 0, 0, 0" for v in videos.values()],
        "individuals:",
        *[f"- {q(n)}" for n in individuals],
        "uniquebodyparts: []",
        "multianimalbodyparts:",
        *[f"- {q(k)}" for k in keypoints],
        "bodyparts: MULTI!",
        "skeleton: []",
    ]
    path = folder / "config.yaml"
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path


def write_label_files(
    folder: Path,
    session: str,
    formats: Sequence[str],
    videos: dict[str, Path],
    keypoints: Sequence[str],
    labels: NoisyLabels,
    individuals: Sequence[str] | None = None,
    rig: Any = None,
) -> list[Path]:
    """Write the per-camera label files of ``formats`` (see the module docstring).

    Args:
        folder: the session folder.
        session: the session's name (names the DeepLabCut folders).
        formats: ``"sleap"``, ``"sleap-session"`` and/or ``"dlc"``.
        videos: camera name -> its video, in the labels' camera order.
        keypoints: (K,) keypoint names.
        labels: the noisy points and scores, (T, C, K, ...); with ``individuals`` the
            keypoint axis holds A * K points, one animal after the other.
        individuals: (A,) the animals, or None for one.
        rig: the cameras (needed by ``"sleap-session"``).

    Returns:
        The files written.
    """
    out = []
    K = len(keypoints)
    for ci, (cam, video) in enumerate(videos.items()):
        pts, sc = labels.points[:, ci], labels.scores[:, ci]
        if individuals is not None:
            pts = pts.reshape(len(pts), len(individuals), K, 2)
            sc = sc.reshape(len(sc), len(individuals), K)
        if "sleap" in formats:
            slp = folder / cam / f"{cam}.slp"
            out.append(write_sleap(slp, video, keypoints, pts, sc, individuals))
        if "dlc" in formats:
            csv_path = folder / "labeled-data" / f"{session}_{cam}" / "CollectedData_synthetic.csv"
            out.append(write_dlc(csv_path, keypoints, pts, individuals))
    if "dlc" in formats and individuals is not None:
        out.append(write_dlc_config(folder, keypoints, individuals, videos))
    if "sleap-session" in formats:
        T, C = labels.points.shape[:2]
        pts = labels.points.reshape(T, C, -1, K, 2)
        sc = labels.scores.reshape(T, C, -1, K)
        out.append(write_sleap_session(folder / f"{session}.slp", rig, videos, keypoints,
                                       pts, sc, individuals))  # fmt: skip
    return out


__all__ = [
    "NoisyLabels",
    "check_label_formats",
    "noisy_labels",
    "write_dlc",
    "write_dlc_config",
    "write_label_files",
    "write_sleap",
    "write_sleap_session",
]
