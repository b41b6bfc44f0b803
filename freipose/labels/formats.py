"""Label importers for DANNCE/Label3D, the original FreiPose, Anipose and JARVIS.

Each ``read_<format>(sources, calibration, mapping, session)`` returns a list of
:class:`~freipose.labels.importing.SourceLabels`; :data:`IMPORTERS` maps ``--format`` names
to them (``dlc`` lives in :mod:`freipose.labels.dlc`, ``sleap`` in :mod:`freipose.labels.sleap`).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from types import MappingProxyType

import numpy as np

from freipose.geometry.camera import CameraRig
from freipose.io.video import VIDEO_SUFFIXES, find_video
from freipose.labels.dlc import read_dlc, read_dlc_table, table_points
from freipose.labels.importing import LabelImportError, SourceLabels
from freipose.labels.mapping import NameMapping
from freipose.labels.sleap import read_sleap
from freipose.labels.views import (
    ViewTable,
    camera_from_name,
    combine_views,
    existing_path,
    frame_from_name,
    match_camera,
)

log = logging.getLogger(__name__)

Importer = Callable[[Sequence[Path], CameraRig | None, NameMapping, str | None], list[SourceLabels]]


# -- DANNCE / Label3D -------------------------------------------------------------------
def read_dannce(
    sources: Sequence[Path],
    calibration: CameraRig | None,
    mapping: NameMapping,
    session: str | None = None,
) -> list[SourceLabels]:
    """``label3d_dannce.mat`` files (MATLAB v5 or v7.3): 3D labels, 2D labels, cameras.

    ``labelData{c}.data_3d`` (N, 3K) mm is kept as the 3D label, ``data_2d`` (N, 2K) per
    camera as the 2D labels and ``data_frame`` (0-based video frames) as the frame index.
    Keypoints are named ``joint1..jointK`` unless the file has ``joint_names`` (rename
    them with a mapping file, e.g. to a DANNCE skeleton's names). The session is the
    folder name.
    """
    from freipose.io.calibration import load_calibration
    from freipose.io.matlab import load_mat

    out = []
    for src in sources:
        path = existing_path(Path(src), "DANNCE label file")
        if path.is_dir():
            cands = sorted(path.glob("*dannce*.mat")) or sorted(path.glob("*.mat"))
            if not cands:
                raise LabelImportError(f"{path}: no label3d_dannce.mat inside")
            path = cands[0]
        mat = load_mat(path)
        if "labelData" not in mat:
            raise LabelImportError(
                f"{path}: no 'labelData' variable (found {sorted(mat)}); expected a DANNCE "
                f"label3d_dannce.mat exported by Label3D"
            )
        rig = load_calibration(path, "dannce")
        cams = list(rig.names)
        ld = mat["labelData"]
        ld = [ld] if isinstance(ld, dict) else list(ld)
        if len(ld) != len(cams):
            raise LabelImportError(f"{path}: {len(ld)} labelData entries for {len(cams)} cameras")
        frames = [np.asarray(d["data_frame"], dtype=np.int64).ravel() for d in ld]
        for c, f in zip(cams[1:], frames[1:]):
            if not np.array_equal(f, frames[0]):
                raise LabelImportError(
                    f"{path}: camera {c!r} labels other frames than {cams[0]!r}; label sync "
                    f"differs between cameras, which this importer does not support"
                )
        d3 = np.asarray(ld[0]["data_3d"], dtype=np.float64)
        n = d3.shape[0]
        if d3.ndim != 2 or d3.shape[1] % 3:
            raise LabelImportError(f"{path}: data_3d must be (N, 3K), got {d3.shape}")
        k = d3.shape[1] // 3
        p3 = d3.reshape(n, k, 3)
        p2 = np.full((n, len(cams), k, 2), np.nan)
        for j, d in enumerate(ld):
            a = np.asarray(d["data_2d"], dtype=np.float64)
            if a.shape != (n, 2 * k):
                raise LabelImportError(
                    f"{path}: camera {cams[j]!r} data_2d has shape {a.shape}, expected {(n, 2 * k)}"
                )
            p2[:, j] = a.reshape(n, k, 2)
        names = mat.get("joint_names")
        kps = [str(x) for x in names] if isinstance(names, list) and len(names) == k else None
        kps = kps or [f"joint{i + 1}" for i in range(k)]
        out.append(
            SourceLabels(
                str(path),
                session or path.parent.name,
                cams,
                kps,
                frames[0],
                p2,
                None,
                p3,
                rig,
                _videos_in(path.parent / "videos", cams),
                None,
                [f"frame {f}" for f in frames[0]],
                positional=kps[0] == "joint1",
            )
        )
    return out


def _videos_in(folder: Path, cams: Sequence[str]) -> dict[str, Path]:
    """``folder/<cam>.<ext>``, ``folder/*_<cam>.<ext>`` or a single video in ``folder/<cam>/``."""
    found: dict[str, Path] = {}
    if not folder.is_dir():
        return found
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES]
    for cam in cams:
        hits = [p for p in files if match_camera(p.stem, [cam]) is not None]
        sub = folder / cam
        if not hits and sub.is_dir():
            hits = [p for p in sub.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES]
        if len(hits) == 1:
            found[cam] = hits[0]
    return found


# -- original FreiPose anno.json + M.json ------------------------------------------------
def read_freipose_json(
    sources: Sequence[Path],
    calibration: CameraRig | None,
    mapping: NameMapping,
    session: str | None = None,
) -> list[SourceLabels]:
    """Original FreiPose ``anno.json`` with ``M.json`` next to it or in the parent folder.

    The file is ``{"%08d.png": {"camK": {"kp_uv", "vis"}, "xyz", "vis3d"}}``, xyz in
    metres. The key's digits are the video frame; ``xyz`` with ``vis3d > 0.5`` is kept as the 3D
    label (converted to mm), other keypoints are triangulated. Keypoints are named
    ``kp0..`` (use ``--skeleton`` with the original's keypoint order, e.g. ``rat``).
    """
    from freipose.io.calibration import load_calibration

    out = []
    for src in sources:
        path = existing_path(Path(src), "FreiPose anno.json")
        if path.is_dir():
            path = path / "anno.json"
            existing_path(path, "FreiPose anno.json")
        try:
            data = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise LabelImportError(f"{path}: not valid JSON ({exc})") from exc
        if not isinstance(data, dict) or not data:
            raise LabelImportError(f"{path}: expected a non-empty object keyed by frame file")
        rig = calibration
        if rig is None:
            for m in (path.parent / "M.json", path.parent.parent / "M.json"):
                if m.is_file():
                    rig = load_calibration(m, "mjson")
                    break
        keys = sorted(data, key=lambda s: frame_from_name(s, str(path)))
        cams: list[str] = []
        k = None
        for key in keys:
            entry = data[key]
            if not isinstance(entry, dict):
                raise LabelImportError(f"{path}: entry {key!r} is not an object")
            for c, v in entry.items():
                if isinstance(v, dict) and "kp_uv" in v:
                    if c not in cams:
                        cams.append(c)
                    kk = len(v["kp_uv"])
                    if k is not None and kk != k:
                        raise LabelImportError(
                            f"{path}: {key!r} camera {c!r} has {kk} keypoints, others {k}"
                        )
                    k = kk
        if k is None:
            raise LabelImportError(f"{path}: no camera entries with kp_uv")
        if rig is not None:
            cams = [c for c in rig.names if c in cams] + [c for c in cams if c not in rig.names]
        n = len(keys)
        p2 = np.full((n, len(cams), k, 2), np.nan)
        vis = np.zeros((n, len(cams), k), dtype=bool)
        p3 = np.full((n, k, 3), np.nan)
        for i, key in enumerate(keys):
            entry = data[key]
            for j, c in enumerate(cams):
                v = entry.get(c)
                if not isinstance(v, dict):
                    continue
                uv = np.asarray(v["kp_uv"], dtype=np.float64).reshape(k, 2)
                vv = np.asarray(v.get("vis", np.ones(k)), dtype=np.float64).reshape(k) > 0.5
                p2[i, j] = np.where(vv[:, None], uv, np.nan)
                vis[i, j] = vv
            xyz = entry.get("xyz", entry.get("kp_xyz"))
            if xyz is not None:
                x = np.asarray(xyz, dtype=np.float64).reshape(k, 3) * 1000.0
                v3 = np.asarray(entry.get("vis3d", np.ones(k)), dtype=np.float64).reshape(k)
                p3[i] = np.where((v3 > 0.5)[:, None], x, np.nan)
        out.append(
            SourceLabels(
                str(path),
                session or path.parent.name,
                cams,
                [f"kp{i}" for i in range(k)],
                np.array([frame_from_name(s, str(path)) for s in keys], dtype=np.int64),
                p2,
                vis,
                p3,
                rig,
                {},
                None,
                keys,
                positional=True,
            )
        )
    return out


# -- Anipose 2D pose files -------------------------------------------------------------
def _pose_tables(folder: Path) -> list[Path]:
    """The 2D pose tables in ``folder``: one per stem, the ``.h5`` where a ``.csv`` copy exists.

    DeepLabCut-layout writers (FreiPose's export among them) write a ``.csv`` and, where
    PyTables is installed, an ``.h5`` of the same table.
    """
    tables = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".h5", ".csv"))
    h5_stems = {p.stem for p in tables if p.suffix.lower() == ".h5"}
    return [p for p in tables if p.suffix.lower() == ".h5" or p.stem not in h5_stems]


def read_anipose(
    sources: Sequence[Path],
    calibration: CameraRig | None,
    mapping: NameMapping,
    session: str | None = None,
    min_likelihood: float = 0.5,
) -> list[SourceLabels]:
    """Anipose 2D pose tables with its ``calibration.toml``.

    The tables are ``pose-2d/<session>_<camera>.h5`` or ``.csv`` (DLC layout, one row per
    video frame; in a folder with both copies of a table, the ``.h5``). Sources are files or
    folders of them; a ``calibration.toml`` among the
    sources, in the folder or its parent is used when ``--calibration`` is not given. Points
    below ``min_likelihood`` are unlabeled; rows without points are skipped.
    """
    from freipose.io.calibration import load_calibration

    files: list[Path] = []
    for s in sources:
        s = existing_path(Path(s), "Anipose pose file or folder")
        if s.is_dir():
            files += _pose_tables(s)
        elif s.suffix.lower() == ".toml":
            if calibration is None:
                calibration = load_calibration(s, "anipose")
        else:
            files.append(s)
    if not files:
        raise LabelImportError(f"no Anipose 2D pose files (.h5/.csv) in {list(sources)}")
    if calibration is None:
        for d in (files[0].parent, files[0].parent.parent):
            if (d / "calibration.toml").is_file():
                calibration = load_calibration(d / "calibration.toml", "anipose")
                break
    by_session: dict[str, list[ViewTable]] = {}
    for path in files:
        cam, sess = camera_from_name(path.stem, path, calibration, mapping)
        table = read_dlc_table(path)
        kps, inds, pts, lik = table_points(table, min_likelihood)
        if inds is not None:
            raise LabelImportError(f"{path}: multi-animal pose tables are not supported here")
        pts = pts[:, 0]
        frames = []
        for r, name in enumerate(table.index):
            try:
                frames.append(int(name))
            except ValueError:
                frames.append(frame_from_name(name, str(path)) if name else r)
        keep = np.isfinite(pts).all(-1).any(-1)
        by_session.setdefault(session or sess or path.parent.name, []).append(
            ViewTable(
                str(path),
                cam,
                kps,
                np.asarray(frames, dtype=np.int64)[keep],
                pts[keep],
                [f"frame {f}" for f in np.asarray(frames)[keep]],
            )
        )
    out = []
    for sess, views in by_session.items():
        videos = {}
        root = Path(views[0].source).parent.parent
        for vt in views:
            p = find_video(Path(vt.source).stem, (root / "videos", root / "videos-raw"))
            if p is not None:
                videos[vt.camera] = p
        out.append(combine_views(sess, views, calibration, videos))
    return out


# -- JARVIS (COCO-style) ----------------------------------------------------------------
def read_jarvis(
    sources: Sequence[Path],
    calibration: CameraRig | None,
    mapping: NameMapping,
    session: str | None = None,
) -> list[SourceLabels]:
    """JARVIS training sets with the calibrations their files list.

    A set is ``annotations/instances_<set>.json`` (COCO keypoints; images
    ``<recording>/<camera>/Frame_<n>.jpg``; (0, 0) = unlabeled); the calibrations are
    OpenCV YAML per camera, relative to the dataset folder.

    Sources are JSON files or dataset folders (all ``annotations/instances_*.json``).
    """
    from freipose.io.calibration import load_calibration

    files: list[Path] = []
    for s in sources:
        s = existing_path(Path(s), "JARVIS annotation file or dataset folder")
        if s.is_dir():
            files += sorted((s / "annotations").glob("instances_*.json")) or sorted(
                s.glob("instances_*.json")
            )
        else:
            files.append(s)
    if not files:
        raise LabelImportError(f"no JARVIS instances_*.json in {list(sources)}")
    views: dict[str, dict[str, list]] = {}
    kps: list[str] | None = None
    rigs: dict[str, CameraRig] = {}
    for path in files:
        try:
            coco = json.loads(path.read_text())
            images = {im["id"]: im for im in coco["images"]}
            cats = coco["categories"]
            anns = coco["annotations"]
        except (json.JSONDecodeError, KeyError, TypeError) as exc:
            raise LabelImportError(
                f"{path}: not a JARVIS/COCO keypoint file ({exc}); expected images, "
                f"annotations and categories with keypoint names"
            ) from exc
        names = [str(x) for x in cats[0].get("keypoints", [])]
        if not names:
            names = [f"kp{i}" for i in range(int(cats[0]["num_keypoints"]))]
        if kps is not None and names != kps:
            raise LabelImportError(f"{path}: keypoints {names} differ from {kps}")
        kps = names
        root = path.parent.parent if path.parent.name == "annotations" else path.parent
        if calibration is None:
            for ds, cams in dict(coco.get("calibrations", {})).items():
                cl = []
                for cam, rel in cams.items():
                    r = load_calibration(root / rel, "jarvis")
                    cl.append(r[0].replace(name=cam))
                rigs[ds] = CameraRig(tuple(cl), {"source_format": "JARVIS YAML"})
        k = len(kps)
        for a in anns:
            im = images.get(a["image_id"])
            if im is None:
                raise LabelImportError(f"{path}: annotation {a.get('id')} names no image")
            parts = str(im["file_name"]).replace("\\", "/").split("/")
            if len(parts) < 3:
                raise LabelImportError(
                    f"{path}: image {im['file_name']!r} is not <recording>/<camera>/<frame>"
                )
            rec, cam = "/".join(parts[:-2]), parts[-2]
            kp = np.asarray(a["keypoints"], dtype=np.float64).reshape(k, 3)
            uv = kp[:, :2].copy()
            unl = (kp[:, 0] == 0) & (kp[:, 1] == 0) | (kp[:, 2] <= 0)
            uv[unl] = np.nan
            tab = views.setdefault(session or rec, {}).setdefault(cam, [])
            tab.append((frame_from_name(parts[-1], str(path)), uv, str(im["file_name"]), path))
    assert kps is not None
    out = []
    for sess, cams in views.items():
        vts = []
        for cam, rows in cams.items():
            rows.sort(key=lambda r: r[0])
            vts.append(
                ViewTable(
                    str(rows[0][3]),
                    cam,
                    kps,
                    np.array([r[0] for r in rows], dtype=np.int64),
                    np.array([r[1] for r in rows]),
                    [r[2] for r in rows],
                )
            )
        rig = calibration
        if rig is None:
            rig = next((r for r in rigs.values() if {v.camera for v in vts} <= set(r.names)), None)
        out.append(combine_views(sess.replace("/", "_"), vts, rig))
    return out


IMPORTERS: Mapping[str, Importer] = MappingProxyType(
    {
        "dlc": read_dlc,
        "sleap": read_sleap,
        "anipose": read_anipose,
        "dannce": read_dannce,
        "jarvis": read_jarvis,
        "freipose": read_freipose_json,
    }
)
