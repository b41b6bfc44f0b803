"""Export ``poses.h5`` to the formats other tools read (described in ``docs/formats.md``).

* ``csv``: a wide CSV, one row per frame: ``frame, time_s, <kp>_x_mm, <kp>_y_mm, <kp>_z_mm,
  <kp>_confidence, ...`` (``<kp>`` the keypoint name with spaces as ``_``; empty cell = NaN),
  and a sidecar ``<file>.csv.json`` naming the layout, every column's keypoint, quantity
  and unit, and the world frame's up direction.
* ``anipose``: Anipose's ``pose-3d`` CSV: ``<kp>_x/_y/_z/_error/_ncams/_score`` per
  keypoint, then ``M_00..M_22``, ``center_0..2`` and ``fnum`` (movement and
  keypoint-MoSeq load it as Anipose output).
* ``dlc3d``: a DeepLabCut-3D style CSV with the three header rows ``scorer / bodyparts /
  coords`` (coords x, y, z) and the frame number as the index.
* ``nwb``: an NWB file with an ndx-pose ``PoseEstimation`` (one 3D
  ``PoseEstimationSeries`` per keypoint, unit mm, confidences, timestamps in seconds) and
  a ``Skeleton`` in the processing module ``behavior`` (pynwb, movement and
  keypoint-MoSeq read it). Needs the optional extra ``nwb`` (``pip install pynwb ndx-pose``).
* ``movement``: a movement poses dataset (netCDF ``.nc``, ``position`` (time, space,
  keypoints, individuals), ``confidence``), read by ``xarray.open_dataset`` and by FreiPose
  (see ``freipose.io.movement``). Needs the optional extra ``movement``.

Poses of several animals (an animal axis, ``individuals``): the CSV has one row per frame
and animal with the columns ``individual`` and ``identity_confidence`` after ``time_s``;
the DLC-3D CSV has DeepLabCut's multi-animal header ``scorer / individuals / bodyparts /
coords``; NWB holds one ``PoseEstimation_<individual>`` per animal, each with its own
``Skeleton`` (``<skeleton>_<individual>``); movement uses its ``individuals`` dimension.
Anipose's format has no animals: export one with ``animal=`` (``freipose export --animal``).

Every writer writes atomically. ``read_*`` functions read the files back (used by the
round-trip tests and handy for users).
"""

from __future__ import annotations

import datetime
import json
import logging
import re
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from freipose.errors import FreiPoseError
from freipose.geometry.projection import project_rig
from freipose.io.atomic import atomic_h5, atomic_path, atomic_write_text
from freipose.io.poses import PoseData, read_poses_h5, write_movement_poses

log = logging.getLogger(__name__)

FORMATS = ("csv", "anipose", "dlc3d", "nwb", "movement")
SUFFIXES = {
    "csv": ".csv",
    "anipose": ".anipose.csv",
    "dlc3d": ".dlc3d.csv",
    "nwb": ".nwb",
    "movement": ".nc",
}


class ExportError(FreiPoseError):
    """An export cannot be written (e.g. a missing optional dependency)."""


def default_output(poses_path: str | Path, fmt: str) -> Path:
    """``x.poses.h5`` -> ``x.csv`` / ``x.anipose.csv`` / ``x.dlc3d.csv`` / ``x.nwb`` / ``x.nc``.

    An unfinished ``x.poses.h5.partial`` gives the same names.
    """
    p = Path(poses_path)
    name = p.name[: -len(".partial")] if p.name.endswith(".poses.h5.partial") else p.name
    stem = name[: -len(".poses.h5")] if name.endswith(".poses.h5") else p.stem
    return p.with_name(stem + SUFFIXES[fmt])


# -- wide CSV ------------------------------------------------------------------------------

WIDE_LAYOUT = "wide: one row per frame"
WIDE_LAYOUT_ANIMALS = "wide: one row per frame and individual"


def column_name(keypoint: str) -> str:
    """A keypoint name as a CSV column prefix: whitespace and commas become ``_``."""
    return re.sub(r"[\s,]+", "_", keypoint.strip())


def _wide_columns(keypoints: tuple[str, ...], animals: bool = False) -> dict[str, dict[str, str]]:
    """Column name -> ``keypoint``, ``quantity``, ``unit`` for every column of the wide CSV.

    ``animals``: the columns ``individual`` and ``identity_confidence`` follow ``time_s``.
    """
    cols = {
        "frame": {"quantity": "video frame index", "unit": ""},
        "time_s": {"quantity": "time (frame / fps)", "unit": "s"},
    }
    if animals:
        cols["individual"] = {"quantity": "animal name", "unit": ""}
        cols["identity_confidence"] = {"quantity": "identity confidence (empty: unknown)",
                                       "unit": "0-1"}  # fmt: skip
    prefixes = [column_name(k) for k in keypoints]
    dupes = sorted({p for p in prefixes if prefixes.count(p) > 1})
    if dupes:
        raise ExportError(
            f"keypoints {[k for k in keypoints if column_name(k) in dupes]} give the same CSV "
            f"column names {dupes}; export them with --format anipose or movement instead"
        )
    for name, pre in zip(keypoints, prefixes):
        for axis in "xyz":
            cols[f"{pre}_{axis}_mm"] = {"keypoint": name, "quantity": axis, "unit": "mm"}
        cols[f"{pre}_confidence"] = {"keypoint": name, "quantity": "confidence", "unit": "0-1"}
    return cols


def wide_frame(data: PoseData) -> pd.DataFrame:
    """The wide table: one row per frame, or per frame and animal (see the module docstring)."""
    multi = data.individuals is not None
    names = list(_wide_columns(tuple(data.keypoints), multi))
    poses, conf = data.animal_poses()  # (T, A, K, 3), (T, A, K)
    T, A = poses.shape[:2]
    poses, conf = poses.reshape(T * A, *poses.shape[2:]), conf.reshape(T * A, -1)
    values: list[Any] = [np.repeat(data.frame_index, A), np.repeat(data.times, A)]
    if multi:
        ident = data.identity_confidence
        values.append(np.tile(np.asarray(data.animal_names, dtype=object), T))
        values.append(np.full(T * A, np.nan) if ident is None else ident.reshape(-1))
    for k in range(len(data.keypoints)):
        values += [poses[:, k, a].astype(np.float64) for a in range(3)]
        values.append(conf[:, k].astype(np.float64))
    return pd.DataFrame(dict(zip(names, values)))


def write_wide_csv(data: PoseData, path: str | Path) -> Path:
    """Write the wide CSV (mm, seconds) and its sidecar ``<path>.json``; returns ``path``."""
    path = Path(path)
    table = wide_frame(data)
    multi = data.individuals is not None
    sidecar = {
        "layout": WIDE_LAYOUT_ANIMALS if multi else WIDE_LAYOUT,
        "keypoints": list(data.keypoints),
        **({"individuals": list(data.animal_names)} if multi else {}),
        "columns": _wide_columns(tuple(data.keypoints), multi),
        "world_frame": "the calibration's world frame (mm)",
        "up": [float(u) for u in data.up],
        "fps": float(data.fps),
    }
    with atomic_path(path) as tmp:
        table.to_csv(tmp, index=False, float_format="%.9g")
    atomic_write_text(Path(f"{path}.json"), json.dumps(sidecar, indent=2) + "\n")
    return path


def read_wide_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[str, ...]]:
    """Read a wide CSV back: (frame_index (T,), poses (T, K, 3), confidence (T, K), keypoints).

    The keypoint names come from the sidecar ``<path>.json`` where it exists, else from
    the column names (spaces then read as ``_``). A CSV of several animals gives one row
    per frame and animal (the ``individual`` column tells them apart).
    """
    df = pd.read_csv(path, dtype={"individual": str})
    if "frame" not in df.columns:
        raise ExportError(f"{path}: no 'frame' column; not a FreiPose wide CSV")
    pres = [
        c[: -len("_confidence")]
        for c in df.columns
        if c.endswith("_confidence") and c != "identity_confidence"
    ]
    side = Path(f"{path}.json")
    kps = tuple(pres)
    if side.is_file():
        named = json.loads(side.read_text(encoding="utf-8")).get("keypoints", [])
        if [column_name(k) for k in named] == pres:
            kps = tuple(named)
    poses = np.stack([df[[f"{p}_{a}_mm" for a in "xyz"]].to_numpy(np.float64) for p in pres], 1)
    conf = np.stack([df[f"{p}_confidence"].to_numpy(np.float64) for p in pres], 1)
    return df["frame"].to_numpy(np.int64), poses, conf, kps


# -- Anipose -------------------------------------------------------------------------------


def _reprojection_stats(data: PoseData) -> tuple[np.ndarray, np.ndarray]:
    """Mean reprojection error (px) and number of contributing views per frame and keypoint.

    The error is against the stored per-view 2D points; NaN where unknown.
    """
    T, K = data.poses.shape[:2]
    err = np.full((T, K), np.nan)
    ncams = np.full((T, K), np.nan)
    p2 = data.extra.get("points2d")
    if data.calibration is None or p2 is None:
        if data.calibration is not None:
            ncams[np.isfinite(data.poses).all(-1)] = len(data.calibration)
        return err, ncams
    proj = project_rig(data.poses.astype(np.float64), data.calibration)  # (T, C, K, 2)
    obs = np.asarray(p2, np.float64)
    c2 = data.extra.get("confidence2d")
    used = np.isfinite(obs).all(-1)
    if c2 is not None:
        used &= np.asarray(c2) > 0
    d = np.linalg.norm(proj - obs, axis=-1)
    d = np.where(used, d, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices give NaN
        err = np.nanmean(d, axis=1)
    ncams = used.sum(1).astype(np.float64)
    found = np.isfinite(data.poses).all(-1)
    err[~found] = np.nan
    ncams[~found] = np.nan
    return err, ncams


def anipose_frame(data: PoseData) -> pd.DataFrame:
    """Anipose's ``pose-3d`` table (see the module docstring).

    Raises:
        ExportError: the poses have an animal axis (Anipose's table holds one animal).
    """
    if data.individuals is not None:
        raise ExportError(
            f"Anipose's pose-3d table holds one animal; these poses hold "
            f"{list(data.individuals)}: export one with --animal NAME, or use --format csv, "
            f"dlc3d, nwb or movement"
        )
    err, ncams = _reprojection_stats(data)
    found = np.isfinite(data.poses).all(-1)
    cols: dict[str, Any] = {}
    for k, name in enumerate(data.keypoints):
        for a, axis in enumerate("xyz"):
            cols[f"{name}_{axis}"] = data.poses[:, k, a].astype(np.float64)
        cols[f"{name}_error"] = err[:, k]
        cols[f"{name}_ncams"] = ncams[:, k]
        cols[f"{name}_score"] = np.where(found[:, k], data.confidence[:, k], np.nan)
    T = data.num_frames
    for i in range(3):
        for j in range(3):
            cols[f"M_{i}{j}"] = np.full(T, float(i == j))
    for i in range(3):
        cols[f"center_{i}"] = np.zeros(T)
    cols["fnum"] = data.frame_index
    return pd.DataFrame(cols)


def write_anipose_csv(data: PoseData, path: str | Path) -> Path:
    """Write the Anipose ``pose-3d`` CSV atomically; returns ``path``."""
    with atomic_path(path) as tmp:
        anipose_frame(data).to_csv(tmp, index=False, float_format="%.9g")
    return Path(path)


def read_anipose_csv(
    path: str | Path,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[str, ...]]:
    """(fnum (T,), poses (T, K, 3), score (T, K), keypoints) from an Anipose 3D CSV."""
    df = pd.read_csv(path)
    kps = tuple(c[: -len("_score")] for c in df.columns if c.endswith("_score"))
    poses = np.stack([df[[f"{k}_{a}" for a in "xyz"]].to_numpy(np.float64) for k in kps], 1)
    score = np.stack([df[f"{k}_score"].to_numpy(np.float64) for k in kps], 1)
    return df["fnum"].to_numpy(np.int64), poses, score, kps


# -- DeepLabCut 3D -------------------------------------------------------------------------


def dlc3d_frame(data: PoseData, scorer: str = "FreiPose") -> pd.DataFrame:
    """DLC-3D style table: MultiIndex columns (scorer, [individuals,] bodyparts, coords).

    The index is the frame; poses of several animals have DeepLabCut's multi-animal
    ``individuals`` level.
    """
    levels = [[scorer], list(data.keypoints), ["x", "y", "z"]]
    names = ["scorer", "bodyparts", "coords"]
    if data.individuals is not None:
        levels.insert(1, list(data.individuals))
        names.insert(1, "individuals")
    cols = pd.MultiIndex.from_product(levels, names=names)
    values = data.poses.reshape(data.num_frames, -1).astype(np.float64)
    return pd.DataFrame(values, columns=cols, index=pd.Index(data.frame_index, name="frame"))


def write_dlc3d_csv(data: PoseData, path: str | Path) -> Path:
    """Write the DeepLabCut-3D style CSV atomically; returns ``path``."""
    with atomic_path(path) as tmp:
        dlc3d_frame(data).to_csv(tmp, float_format="%.9g")
    return Path(path)


def read_dlc3d_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """(frame (T,), poses (T, [A,] K, 3), keypoints) from a DLC-3D style CSV.

    A multi-animal header (4 rows) gives poses (T, A, K, 3).
    """
    with open(path, encoding="utf-8") as fh:
        head = [fh.readline().split(",")[0] for _ in range(4)]
    multi = head[1] == "individuals"
    df = pd.read_csv(path, header=[0, 1, 2, 3] if multi else [0, 1, 2], index_col=0)
    kps = tuple(dict.fromkeys(df.columns.get_level_values(2 if multi else 1)))
    shape = (len(df), -1, len(kps), 3) if multi else (len(df), len(kps), 3)
    poses = df.to_numpy(np.float64).reshape(shape)
    return df.index.to_numpy(np.int64), poses, kps


# -- NWB -----------------------------------------------------------------------------------


def _require_nwb() -> tuple[Any, Any]:
    try:
        import ndx_pose
        import pynwb
    except ImportError as exc:
        raise ExportError(
            "NWB export needs the optional packages pynwb and ndx-pose: "
            "pip install 'freipose[nwb]' (or pip install pynwb ndx-pose)"
        ) from exc
    return pynwb, ndx_pose


def write_nwb(
    data: PoseData,
    path: str | Path,
    session_description: str = "3D poses from FreiPose",
    session_start_time: datetime.datetime | None = None,
    identifier: str | None = None,
    subject: str = "animal",
) -> Path:
    """Write an NWB file with an ndx-pose ``PoseEstimation`` in processing module ``behavior``.

    Args:
        data: the poses.
        path: the output file.
        session_description: the NWB session description.
        session_start_time: recording start (timezone-aware); default the Unix epoch in UTC
            (NWB requires a value; pass the real start when known).
        identifier: NWB identifier; default the session name from the provenance.
        subject: the subject's name in the skeleton.

    Returns:
        ``path``.

    Raises:
        ExportError: pynwb or ndx-pose is missing, or a start time without a time zone.
    """
    pynwb, ndx_pose = _require_nwb()
    start = session_start_time or datetime.datetime(1970, 1, 1, tzinfo=datetime.timezone.utc)
    if start.tzinfo is None:
        raise ExportError(
            "session_start_time must be timezone-aware (e.g. 2024-05-01T10:00:00+02:00)"
        )
    prov = dict(data.provenance)
    ident = identifier or str(prov.get("session", Path(path).stem))
    nwb = pynwb.NWBFile(
        session_description=session_description, identifier=ident, session_start_time=start
    )
    names = list(data.keypoints)
    edges = None
    if data.skeleton is not None:
        pairs = []
        for a, b in data.skeleton.limbs:
            if len(a) == 1 and len(b) == 1:  # NWB edges join nodes; midpoint limbs are skipped
                pairs.append([int(a[0]), int(b[0])])
        edges = np.asarray(pairs, dtype=np.uint8 if len(names) < 256 else np.uint16).reshape(-1, 2)
    skel_name = data.skeleton.name if data.skeleton is not None else "skeleton"
    times = data.times.astype(np.float64)
    frame_desc = "world frame of the FreiPose calibration, millimetres, up = " + ", ".join(
        f"{u:g}" for u in data.up
    )
    multi = data.individuals is not None
    skeletons, estimations = [], []
    for i, animal in enumerate(data.animal_names):
        one = data.animal(i)
        skeleton = ndx_pose.Skeleton(
            name=f"{skel_name}_{animal}" if multi else skel_name, nodes=names, edges=edges
        )
        series: list[Any] = []
        for k, name in enumerate(names):
            series.append(
                ndx_pose.PoseEstimationSeries(
                    name=name,
                    description=f"3D position of {name}" + (f" of {animal}" if multi else ""),
                    data=one.poses[:, k, :].astype(np.float64),
                    unit="mm",
                    reference_frame=frame_desc,
                    timestamps=times if not series else series[0],
                    confidence=one.confidence[:, k].astype(np.float64),
                    confidence_definition="FreiPose confidence in [0, 1]; 0 where not found",
                )
            )
        who = animal if multi else subject
        skeletons.append(skeleton)
        estimations.append(
            ndx_pose.PoseEstimation(
                name=f"PoseEstimation_{animal}" if multi else "PoseEstimation",
                pose_estimation_series=series,
                description=(
                    f"3D poses of {who} estimated by FreiPose from the synchronized videos "
                    + ", ".join(str(v) for v in dict(prov.get("videos", {})).values())
                ),
                scorer=str(prov.get("model_sha256", "FreiPose")),
                source_software="FreiPose",
                source_software_version=str(prov.get("freipose_version", "")),
                skeleton=skeleton,
            )
        )
    module = nwb.create_processing_module(name="behavior", description="processed behavioral data")
    module.add(ndx_pose.Skeletons(skeletons=skeletons))
    for pe in estimations:
        module.add(pe)
    with atomic_h5(path) as f, pynwb.NWBHDF5IO(file=f, mode="w") as io:
        io.write(nwb)
    return Path(path)


def read_nwb(
    path: str | Path, individual: str | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[str, ...]]:
    """(timestamps (T,), poses (T, K, 3), confidence (T, K), keypoints) from our NWB export.

    Args:
        path: the file.
        individual: the animal of a file of several (``PoseEstimation_<individual>``).
    """
    pynwb, _ = _require_nwb()
    with pynwb.NWBHDF5IO(str(path), mode="r") as io:
        nwb = io.read()
        name = "PoseEstimation" if individual is None else f"PoseEstimation_{individual}"
        pe = nwb.processing["behavior"][name]
        kps = tuple(pe.skeleton.nodes[:])
        ser = pe.pose_estimation_series
        poses = np.stack([np.asarray(ser[k].data[:]) for k in kps], 1)
        conf = np.stack([np.asarray(ser[k].confidence[:]) for k in kps], 1)
        times = np.asarray(ser[kps[0]].timestamps[:])
    return times, poses, conf, kps


# -- dispatch ------------------------------------------------------------------------------


def export_poses(
    poses_path: str | Path,
    fmt: str,
    output: str | Path | None = None,
    animal: str | None = None,
    **kwargs: Any,
) -> Path:
    """Export a ``poses.h5`` file to ``fmt`` (one of :data:`FORMATS`); returns the output path.

    Args:
        poses_path: the poses file.
        fmt: the format.
        output: the output file (default: :func:`default_output`).
        animal: export only this animal of poses with an animal axis (without an axis).
        kwargs: passed to :func:`write_nwb`.

    Raises:
        ExportError: an unknown format or animal, or a missing optional dependency.
    """
    if fmt not in FORMATS:
        raise ExportError(f"unknown export format {fmt!r}; choose one of {', '.join(FORMATS)}")
    if fmt == "nwb":
        _require_nwb()  # fail before reading a large file
    data = read_poses_h5(poses_path)
    if animal is not None:
        if data.individuals is None or animal not in data.individuals:
            held = "one animal without names" if data.individuals is None else data.individuals
            raise ExportError(
                f"{poses_path}: no animal {animal!r} (the poses hold {held}); pass one of "
                f"those names to --animal, or leave it out to export every animal"
            )
        data = data.animal(animal)
    out = Path(output) if output is not None else default_output(poses_path, fmt)
    if fmt == "csv":
        return write_wide_csv(data, out)
    if fmt == "anipose":
        return write_anipose_csv(data, out)
    if fmt == "dlc3d":
        return write_dlc3d_csv(data, out)
    if fmt == "movement":
        return write_movement_poses(data, out)
    return write_nwb(data, out, **kwargs)
