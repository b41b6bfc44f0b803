"""DeepLabCut labels: ``CollectedData_<scorer>.h5`` / ``.csv`` (and 2D pose tables).

A DLC table has a column header of 3 rows ``scorer / bodyparts / coords`` (single animal)
or 4 rows ``scorer / individuals / bodyparts / coords`` (multi-animal); ``coords`` are
``x, y`` (labels) or ``x, y, likelihood`` (predictions). Rows are images, named by a
path ``labeled-data/<video>/img0123.png`` (or three index columns in newer files); the
digits of the image name are the video frame index.

The ``.h5`` files are pandas HDF5 tables; they are read with h5py directly (PyTables'
"table" layout that DeepLabCut writes), or with pandas when PyTables is installed.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import logging
import pickle
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from freipose.errors import InputFileError
from freipose.geometry.camera import CameraRig
from freipose.io.atomic import atomic_path, atomic_write_text
from freipose.io.video import find_video
from freipose.labels.importing import LabelImportError, SourceLabels
from freipose.labels.mapping import NameMapping
from freipose.labels.views import ViewTable, camera_from_name, combine_views, frame_from_name

log = logging.getLogger(__name__)

HEADER_NAMES = ("scorer", "individuals", "bodyparts", "coords")


@dataclass(frozen=True, eq=False)
class DlcTable:
    """A DLC table.

    Attributes:
        path: the file read.
        index: (N,) row names.
        columns: (C,) column tuples (scorer, [individual,] bodypart, coord).
        values: (N, C) float64 (NaN = missing).
    """

    path: Path
    index: list[str]
    columns: list[tuple[str, ...]]
    values: np.ndarray
    levels: tuple[str, ...]


class _SafeUnpickler(pickle.Unpickler):
    """Unpickles only plain data (lists, tuples, strings, numbers): no classes, no code."""

    def find_class(self, module: str, name: str) -> None:  # noqa: D102
        raise pickle.UnpicklingError(f"refusing to load {module}.{name} from a DLC .h5 file")


def _unpickle(raw: object) -> object:
    data = raw.tobytes() if isinstance(raw, np.ndarray) else bytes(raw)
    return _SafeUnpickler(io.BytesIO(data), encoding="utf-8").load()


def _read_h5_table(path: Path) -> DlcTable:
    import h5py

    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise LabelImportError(
            f"{path}: not a readable HDF5 file ({exc}); is it truncated? DeepLabCut can "
            f"rewrite it, or use the CollectedData .csv instead"
        ) from exc
    with f:
        keys = list(f.keys())
        key = "df_with_missing" if "df_with_missing" in f else (keys[0] if keys else None)
        if key is None or not isinstance(f[key], h5py.Group):
            raise LabelImportError(f"{path}: no pandas table inside (groups: {keys})")
        g = f[key]
        if "table" not in g:
            try:
                import pandas as pd

                df = pd.read_hdf(path, key)
            except ImportError as exc:
                raise LabelImportError(
                    f"{path}: this is pandas' 'fixed' HDF5 layout, which needs PyTables to "
                    f"read; install it (pip install tables) or use the CollectedData .csv"
                ) from exc
            return _from_frame(path, df)
        try:
            t = g["table"][()]
            info = _unpickle(g.attrs["info"]) if "info" in g.attrs else {}
        except (OSError, KeyError, pickle.UnpicklingError, EOFError, ValueError) as exc:
            raise LabelImportError(f"{path}: the table cannot be read ({exc}); truncated?") from exc
        tattrs = g["table"].attrs
        blocks = sorted(n for n in t.dtype.names if n.startswith("values_block_"))
        idx_fields = [n for n in t.dtype.names if not n.startswith("values_block_")]
        columns: list[tuple[str, ...]] = []
        vals = []
        for b in blocks:
            kind = _unpickle(tattrs[f"{b}_kind"])
            cols = [tuple(str(x) for x in c) for c in kind]
            v = np.asarray(t[b], dtype=np.float64).reshape(len(t), -1)
            if v.shape[1] != len(cols):
                raise LabelImportError(
                    f"{path}: {b} has {v.shape[1]} values for {len(cols)} columns"
                )
            columns += cols
            vals.append(v)
        index = []
        for row in t:
            parts = []
            for n in idx_fields:
                x = row[n]
                parts.append(x.decode() if isinstance(x, bytes) else str(x))
            index.append("/".join(p for p in parts if p))
        levels: tuple[str, ...] = ()
        if isinstance(info, dict):
            ci = info.get(1, {})
            names = ci.get("names") if isinstance(ci, dict) else None
            if names:
                levels = tuple(str(x) for x in names)
        values = np.concatenate(vals, axis=1) if vals else np.zeros((len(t), 0))
        if not levels:
            levels = HEADER_NAMES if len(columns[0]) == 4 else ("scorer", "bodyparts", "coords")
        return DlcTable(path, index, columns, values, levels)


def _from_frame(path: Path, df: object) -> DlcTable:
    import pandas as pd

    if not isinstance(df, pd.DataFrame):
        raise LabelImportError(f"{path}: the HDF5 file holds no DeepLabCut table (a DataFrame)")
    idx = ["/".join(str(x) for x in i) if isinstance(i, tuple) else str(i) for i in df.index]
    cols = [tuple(str(x) for x in c) for c in df.columns]
    levels = tuple(str(n) for n in df.columns.names)
    return DlcTable(path, idx, cols, df.to_numpy(dtype=np.float64), levels)


def _read_csv_table(path: Path) -> DlcTable:
    try:
        rows = list(csv.reader(path.read_text(encoding="utf-8-sig").splitlines()))
    except (OSError, UnicodeDecodeError) as exc:
        raise LabelImportError(f"{path}: cannot read the CSV ({exc})") from exc
    header = []
    for r in rows:
        label = next((x for x in r if x), "")
        if label in HEADER_NAMES and len(header) < 4:
            header.append(r)
            if label == "coords":
                break
        else:
            break
    labels = [next((x for x in r if x), "") for r in header]
    if not header or labels[0] != "scorer" or labels[-1] != "coords":
        raise LabelImportError(
            f"{path}: not a DeepLabCut table; expected header rows scorer / [individuals /] "
            f"bodyparts / coords, found {[r[:2] for r in rows[:4]]}"
        )
    coords = header[-1]
    first = next((i for i, x in enumerate(coords) if x in ("x", "y", "likelihood")), None)
    if first is None:
        raise LabelImportError(f"{path}: the coords row has no x/y columns")
    columns = [tuple(r[c] for r in header) for c in range(first, len(coords))]
    index, values = [], []
    for ln, r in enumerate(rows[len(header) :], start=len(header) + 1):
        if not any(r):
            continue
        if len(r) != len(coords):
            raise LabelImportError(
                f"{path}: line {ln} has {len(r)} fields, the header {len(coords)}; is the file "
                f"truncated?"
            )
        index.append("/".join(x for x in r[:first] if x))
        try:
            values.append([float(x) if x.strip() else np.nan for x in r[first:]])
        except ValueError as exc:
            raise LabelImportError(f"{path}: line {ln}: {exc}") from exc
    v = np.array(values, dtype=np.float64).reshape(len(values), len(columns))
    return DlcTable(path, index, columns, v, tuple(labels))


def read_dlc_table(path: str | Path) -> DlcTable:
    """Read a DLC ``.h5`` or ``.csv`` table (labels or predictions)."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"DeepLabCut table not found: {path}")
    if path.suffix.lower() in (".h5", ".hdf5"):
        return _read_h5_table(path)
    if path.suffix.lower() == ".csv":
        return _read_csv_table(path)
    raise LabelImportError(f"{path}: expected a DeepLabCut .h5 or .csv table")


def table_points(
    table: DlcTable, min_likelihood: float | None = None
) -> tuple[list[str], list[str] | None, np.ndarray, np.ndarray | None]:
    """Split a table into per-(row, individual) points.

    Returns:
        ``(keypoints, individuals, points (N, I, K, 2), likelihood (N, I, K) or None)``;
        individuals is None for single-animal tables (I = 1).
    """
    multi = len(table.columns[0]) == 4
    kps: list[str] = []
    inds: list[str] = []
    for c in table.columns:
        ind, bp = (c[1], c[2]) if multi else ("", c[1])
        if bp not in kps:
            kps.append(bp)
        if ind not in inds:
            inds.append(ind)
    n = len(table.index)
    pts = np.full((n, len(inds), len(kps), 2), np.nan)
    lik = None
    for j, c in enumerate(table.columns):
        ind, bp, coord = (c[1], c[2], c[3]) if multi else ("", c[1], c[2])
        i, k = inds.index(ind), kps.index(bp)
        if coord in ("x", "y"):
            pts[:, i, k, "xy".index(coord)] = table.values[:, j]
        elif coord == "likelihood":
            if lik is None:
                lik = np.full((n, len(inds), len(kps)), np.nan)
            lik[:, i, k] = table.values[:, j]
    if lik is not None and min_likelihood is not None:
        pts[~(lik >= min_likelihood)] = np.nan
    return kps, (inds if multi else None), pts, lik


def _table_file(folder: Path) -> Path:
    cands = sorted(folder.glob("CollectedData_*.h5")) or sorted(folder.glob("CollectedData_*.csv"))
    if not cands:
        raise LabelImportError(
            f"{folder}: no CollectedData_*.h5 or .csv; pass DeepLabCut labeled-data folders "
            f"(one per camera), their CollectedData files, or a project folder"
        )
    return cands[0]


def _expand(sources: Sequence[Path]) -> list[Path]:
    """Source arguments -> CollectedData files (a project or labeled-data folder expands)."""
    out: list[Path] = []
    for s in sources:
        s = Path(s)
        if not s.exists():
            raise InputFileError(f"DeepLabCut source not found: {s}")
        if s.is_file():
            out.append(s)
        elif (s / "labeled-data").is_dir():
            out += [_table_file(d) for d in sorted((s / "labeled-data").iterdir()) if d.is_dir()]
        elif list(s.glob("CollectedData_*")):
            out.append(_table_file(s))
        else:
            subs = [
                d for d in sorted(s.iterdir()) if d.is_dir() and list(d.glob("CollectedData_*"))
            ]
            if not subs:
                raise LabelImportError(f"{s}: no DeepLabCut labels (CollectedData_*) found")
            out += [_table_file(d) for d in subs]
    return out


def _find_video(folder: Path, name: str) -> Path | None:
    return find_video(name, (folder.parent.parent / "videos", folder.parent))


def read_dlc(
    sources: Sequence[Path],
    calibration: CameraRig | None,
    mapping: NameMapping,
    session: str | None = None,
) -> list[SourceLabels]:
    """DeepLabCut labeled-data folders (one per camera) -> source labels per session.

    The folder name picks camera and session: ``--camera-map FOLDER=CAMERA`` first, else a
    calibration camera name inside the folder name (``run1_cam0`` -> session ``run1``,
    camera ``cam0``), else (no calibration) the folder name is the camera.
    """
    by_session: dict[str, list[tuple[ViewTable, Path | None]]] = {}
    for path in _expand(sources):
        folder = path.parent
        fname = folder.name
        table = read_dlc_table(path)
        if not table.index:
            raise LabelImportError(f"{path}: the table has no rows")
        cam_src, sess = camera_from_name(fname, path, calibration, mapping, kind="folder")
        sess = (
            session
            or sess
            or (folder.parent.parent.name if folder.parent.name == "labeled-data" else folder.name)
        )
        kps, inds, pts, _ = table_points(table)
        rows, fidx, names, indiv = [], [], [], []
        for r, name in enumerate(table.index):
            f = frame_from_name(name, str(path))
            for i in range(pts.shape[1]):
                if inds is not None and not np.isfinite(pts[r, i]).any():
                    continue  # an animal absent from this image
                rows.append(pts[r, i])
                fidx.append(f)
                names.append(name + (f" ({inds[i]})" if inds else ""))
                indiv.append(inds[i] if inds else "")
        vt = ViewTable(
            str(path),
            cam_src,
            kps,
            np.array(fidx, dtype=np.int64),
            np.array(rows).reshape(len(rows), len(kps), 2),
            names,
            indiv if inds is not None else None,
        )
        by_session.setdefault(sess, []).append((vt, _find_video(folder, fname), folder))
    out = []
    for sess, items in by_session.items():
        videos = {vt.camera: p for vt, p, _ in items if p is not None}
        vts = [vt for vt, _, _ in items]
        if not videos:
            vts, videos = _image_folders_as_videos(sess, vts, [d for _, _, d in items])
        out.append(combine_views(sess, vts, None, videos))
    return out


def _image_folders_as_videos(
    session: str, views: list[ViewTable], folders: list[Path]
) -> tuple[list[ViewTable], dict[str, Path]]:
    """Without videos, use the labeled-data image folders as the cameras' frame sources.

    This works when every folder of the session holds images of the same frames (by the
    digits of their names) covering all labeled rows: the frame index of each row becomes
    the position of its image in the folder (what :class:`~freipose.io.video.FrameSource`
    reads as that frame). Otherwise the views are returned unchanged, without videos.
    """
    from freipose.io.video import list_images

    frame_lists = []
    for d in folders:
        try:
            frames = [frame_from_name(p.name, str(d)) for p in list_images(d)]
        except LabelImportError:
            frames = []
        frame_lists.append(frames)
    first = frame_lists[0]
    usable = (
        bool(first)
        and len(set(first)) == len(first)
        and first == sorted(first)
        and all(f == first for f in frame_lists[1:])
        and all(np.isin(vt.frame_index, first).all() for vt in views)
    )
    if not usable:
        log.info(
            "session %s: no videos and the labeled-data folders do not hold the same labeled "
            "frames, so the labels list no frame sources",
            session,
        )
        return views, {}
    order = np.asarray(first, dtype=np.int64)
    log.info(
        "session %s: no videos; using the labeled-data image folders as frame sources (frame "
        "index = image position, %d images per camera)",
        session,
        len(order),
    )
    remapped = [
        dataclasses.replace(vt, frame_index=np.searchsorted(order, vt.frame_index)) for vt in views
    ]
    return remapped, {vt.camera: d for vt, d in zip(views, folders)}


def dlc_table_text(
    scorer: str,
    keypoints: Sequence[str],
    index: Sequence[str],
    points: np.ndarray,
    likelihood: np.ndarray | None = None,
    individuals: Sequence[str] | None = None,
) -> str:
    """A DLC CSV: rows ``index`` (N,), points (N, K, 2) NaN = missing.

    With ``individuals`` (A,), a multi-animal table (header ``scorer / individuals /
    bodyparts / coords``) of points (N, A, K, 2) and likelihoods (N, A, K).
    """
    coords = ["x", "y"] + (["likelihood"] if likelihood is not None else [])
    if individuals is None:
        points = points[:, None]
        likelihood = None if likelihood is None else likelihood[:, None]
    names = [""] if individuals is None else [str(a) for a in individuals]
    cols = [(a, k) for a in range(len(names)) for k in range(len(keypoints))]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["scorer"] + [scorer] * (len(cols) * len(coords)))
    if individuals is not None:
        w.writerow(["individuals"] + [names[a] for a, _ in cols for _ in coords])
    w.writerow(["bodyparts"] + [keypoints[k] for _, k in cols for _ in coords])
    w.writerow(["coords"] + coords * len(cols))
    for r, name in enumerate(index):
        vals = []
        for a, k in cols:
            for c in coords:
                x = likelihood[r, a, k] if c == "likelihood" else points[r, a, k, "xy".index(c)]
                vals.append("" if not np.isfinite(x) else repr(float(x)))
        w.writerow([name] + vals)
    return buf.getvalue()


def write_dlc_table(
    path: Path,
    scorer: str,
    keypoints: Sequence[str],
    index: Sequence[str],
    points: np.ndarray,
    likelihood: np.ndarray | None = None,
    individuals: Sequence[str] | None = None,
) -> list[Path]:
    """Write ``path`` (.csv) and, when PyTables is installed, the matching ``.h5``.

    ``individuals``: a multi-animal table (see :func:`dlc_table_text`).
    """
    text = dlc_table_text(scorer, keypoints, index, points, likelihood, individuals)
    atomic_write_text(path, text)
    written = [path]
    try:
        import tables  # noqa: F401
    except ImportError:
        log.info("PyTables is not installed: wrote %s only (DeepLabCut converts it)", path.name)
        return written
    import pandas as pd

    header = [0, 1, 2] if individuals is None else [0, 1, 2, 3]
    df = pd.read_csv(io.StringIO(text), header=header, index_col=0)
    h5 = path.with_suffix(".h5")
    with atomic_path(h5) as tmp:
        df.to_hdf(tmp, key="df_with_missing", format="table", mode="w")
    return written + [h5]
