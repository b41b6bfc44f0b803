"""Other tools' calibration formats, dispatched to by :mod:`freipose.io.calibration`.

Format names (``--format``) and what they read/write (details in ``docs/formats.md``):

* ``mjson`` (``*.json``): the original FreiPose / FreiCalib ``M.json`` with ``K``,
  ``dist`` and ``M`` dicts keyed by camera name; ``M`` is the 4x4 camera→world pose in
  **metres**. Read and write.
* ``anipose`` (``*.toml`` with ``--format anipose``): Anipose's ``calibration.toml``;
  translations in the units they were stored in (``units`` option, default mm). Written
  without FreiPose's ``[metadata]`` table. Read and write.
* ``jarvis`` (a folder of ``<camera>.yaml``, or one ``*.yaml``): OpenCV FileStorage YAML as
  written by JARVIS's calibration tool, ``intrinsicMatrix`` = Kᵀ, ``distortionCoefficients``,
  ``R`` = Rᵀ (MATLAB convention) and ``T`` = t in mm. Read and write.
* ``dannce`` (``*.mat``): camera parameters in DANNCE/Label3D ``label3d_dannce.mat``
  (``params`` cell of structs with ``K``, ``RDistort``, ``TDistort``, ``r``, ``t`` in
  MATLAB row-vector convention, skew kept; mm). Read only.

M.json, JARVIS and DANNCE files store no image size. FreiPose writes it as an extra key
that those tools ignore (``img_size`` in M.json, ``image_width``/``image_height`` in the
YAML); when it is absent the size comes from a video of the camera next to the file
(``<anything>_<camera>.<video suffix>`` or ``<camera>.<suffix>``), else it is estimated as
``2 * principal point + 1`` (logged), and the rig's ``metadata.image_size_estimated`` lists
those cameras.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
import tomli_w

from freipose.geometry.camera import Camera, CameraRig
from freipose.geometry.transforms import transform
from freipose.io.atomic import atomic_write_text
from freipose.io.calibration_toml import (
    UNIT_SCALE_TO_MM,
    CalibrationFormatError,
    as_rotation,
    read_calibration_toml,
    rig_to_toml_dict,
    toml_value,
)
from freipose.io.natsort import natural_key
from freipose.io.toml import check_keys
from freipose.io.video import VIDEO_SUFFIXES

log = logging.getLogger(__name__)

ESTIMATED_KEY = "image_size_estimated"


class UnknownCameraError(CalibrationFormatError, KeyError):
    """A camera name that the rig does not have."""


_YAML_SUFFIXES = (".yaml", ".yml")


# -- helpers ---------------------------------------------------------------------------
def _make_camera(source: str, name: str, **kw: Any) -> Camera:
    try:
        return Camera(name=name, **kw)
    except ValueError as exc:
        raise CalibrationFormatError(f"{source}: {exc}") from exc


def estimate_size_from_principal_point(K: np.ndarray) -> tuple[int, int]:
    """Image size ``(w, h)`` guessed from a centred principal point: ``2 * (cx, cy) + 1``."""
    K = np.asarray(K, dtype=np.float64)
    return (max(1, int(round(2 * K[0, 2] + 1))), max(1, int(round(2 * K[1, 2] + 1))))


def video_sizes(folder: Path, names: Sequence[str]) -> dict[str, tuple[int, int]]:
    """Frame sizes of the cameras' videos in ``folder`` (``<x>_<cam>.mp4`` or ``<cam>.mp4``)."""
    if not folder.is_dir():
        return {}
    videos = sorted(
        p
        for p in folder.iterdir()
        if p.suffix.lower() in VIDEO_SUFFIXES and not p.name.startswith(".")
    )
    if not videos:
        return {}
    import cv2

    out: dict[str, tuple[int, int]] = {}
    for name in names:
        pat = re.compile(r"(^|[_\-. ])" + re.escape(name) + r"$")
        for v in videos:
            if not pat.search(v.stem):
                continue
            cap = cv2.VideoCapture(str(v))
            w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
            cap.release()
            if w > 0 and h > 0:
                out[name] = (w, h)
                break
    return out


def _fill_sizes(
    source: Path,
    names: Sequence[str],
    Ks: Sequence[np.ndarray],
    stored: Mapping[str, Any],
) -> tuple[list[tuple[int, int]], list[str]]:
    """Image sizes: stored ones, else from videos next to ``source``, else estimated."""
    sizes: dict[str, tuple[int, int]] = {}
    for n in names:
        if n in stored and stored[n] is not None:
            s = np.asarray(stored[n]).ravel()
            if s.size != 2:
                raise CalibrationFormatError(
                    f"{source}: image size of {n!r} must be [w, h], got {stored[n]!r}"
                )
            sizes[n] = (int(s[0]), int(s[1]))
    missing = [n for n in names if n not in sizes]
    if missing:
        folder = source if source.is_dir() else source.parent
        sizes.update(video_sizes(folder, missing))
    estimated = [n for n in names if n not in sizes]
    for n, K in zip(names, Ks):
        if n in estimated:
            sizes[n] = estimate_size_from_principal_point(K)
    if estimated:
        log.info(
            "%s stores no image size for %s; estimated from the principal point (2*c+1) as %s "
            "unless given otherwise (freipose calib convert --size WxH)",
            source,
            estimated,
            {n: sizes[n] for n in estimated},
        )
    return [sizes[n] for n in names], estimated


def _metadata(extra: Mapping[str, Any], estimated: Sequence[str], **facts: Any) -> dict[str, Any]:
    md = dict(extra)
    md.update(facts)
    md["units"] = "mm"
    if estimated:
        md[ESTIMATED_KEY] = list(estimated)
    else:
        md.pop(ESTIMATED_KEY, None)
    return md


# -- FreiPose / FreiCalib M.json -------------------------------------------------------
def read_mjson(path: str | Path) -> CameraRig:
    """Read a FreiPose/FreiCalib ``M.json`` (camera→world 4x4 poses in metres) into mm."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CalibrationFormatError(f"{path}: not a valid JSON file ({exc})") from exc
    if not isinstance(data, dict) or not all(
        isinstance(data.get(k), dict) for k in ("K", "dist", "M")
    ):
        found = f"keys {sorted(data)}" if isinstance(data, dict) else type(data).__name__
        raise CalibrationFormatError(
            f"{path}: an M.json needs the objects 'K', 'dist' and 'M', each keyed by camera "
            f"name (e.g. {{'K': {{'cam0': 3x3}}, 'dist': {{'cam0': [k1,k2,p1,p2,k3]}}, "
            f"'M': {{'cam0': 4x4 camera-to-world in metres}}}}); found {found}"
        )
    check_keys(data, ("K", "dist", "M", "img_size", "metadata"), str(path), CalibrationFormatError)
    names = sorted(data["K"], key=natural_key)
    if not names:
        raise CalibrationFormatError(f"{path}: 'K' lists no cameras")
    for key in ("dist", "M", "img_size"):
        if isinstance(data.get(key), dict):  # every camera needs its 'K'
            where = f"{path}: '{key}' (keyed by the cameras of 'K')"
            check_keys(data[key], names, where, CalibrationFormatError)
    for key in ("dist", "M"):
        lacking = [n for n in names if n not in data[key]]
        if lacking:
            raise CalibrationFormatError(
                f"{path}: cameras {lacking} have a 'K' but no '{key}' entry"
            )
    Ks = []
    for n in names:
        K = np.asarray(data["K"][n], dtype=np.float64)
        if K.size != 9:
            raise CalibrationFormatError(f"{path}: K of {n!r} must be 3x3, got shape {K.shape}")
        Ks.append(K.reshape(3, 3))
    sizes, estimated = _fill_sizes(path, names, Ks, data.get("img_size", {}) or {})
    cams = []
    for n, K, size in zip(names, Ks, sizes):
        M = np.asarray(data["M"][n], dtype=np.float64)
        if M.size != 16:
            raise CalibrationFormatError(f"{path}: M of {n!r} must be 4x4, got shape {M.shape}")
        M = M.reshape(4, 4)
        if not np.allclose(M[3], (0, 0, 0, 1), atol=1e-9):
            raise CalibrationFormatError(
                f"{path}: M of {n!r} must be a rigid 4x4 transform with last row [0, 0, 0, 1], "
                f"got {M[3].tolist()}"
            )
        R_cw = as_rotation(M[:3, :3], str(path), n)
        center_mm = M[:3, 3] * 1000.0
        R = R_cw.T
        cams.append(
            _make_camera(
                str(path),
                n,
                size=size,
                K=K,
                dist=np.asarray(data["dist"][n], dtype=np.float64).ravel(),
                R=R,
                t=-R @ center_mm,
            )
        )
    stored = data.get("metadata")
    extra: dict[str, Any] = stored if isinstance(stored, dict) else {}
    facts = (
        {}
        if extra
        else {
            "world": "as in the M.json (FreiCalib: the frame of its first camera)",
            "source_format": "FreiPose M.json",
        }
    )
    return CameraRig(tuple(cams), _metadata(extra, estimated, **facts))


def write_mjson(rig: CameraRig, path: str | Path) -> None:
    """Write a FreiPose/FreiCalib ``M.json``: ``M`` = camera→world 4x4 in metres.

    The image sizes (``img_size``) and the rig metadata (``metadata``) are added as extra
    keys; FreiPose reads only ``K``, ``dist`` and ``M``.
    """
    odd = [n for n in rig.names if not re.fullmatch(r"cam\d+", n)]
    if odd:
        log.warning(
            "FreiPose finds cameras by the names cam0, cam1, ...; %s will keep their names", odd
        )
    M = {}
    for cam in rig:
        M[cam.name] = transform(cam.R.T, cam.center / 1000.0).tolist()  # camera→world, m
    data = {
        "K": {c.name: c.K.tolist() for c in rig},
        "dist": {c.name: c.dist.tolist() for c in rig},
        "M": M,
        "img_size": {c.name: [int(c.size[0]), int(c.size[1])] for c in rig},
        "metadata": toml_value(dict(rig.metadata)),
    }
    atomic_write_text(path, json.dumps(data, indent=2) + "\n")


# -- Anipose calibration.toml ----------------------------------------------------------
def read_anipose_calibration(path: str | Path, units: str = "mm") -> CameraRig:
    """Read an Anipose ``calibration.toml`` whose translations are in ``units`` (mm, cm, m).

    A ``[metadata] units`` entry in the file takes precedence over ``units``.
    """
    if units not in UNIT_SCALE_TO_MM:
        raise CalibrationFormatError(
            f"units must be one of {sorted(UNIT_SCALE_TO_MM)}, got {units!r}"
        )
    return read_calibration_toml(path, units=units)


def anipose_toml_text(rig: CameraRig, units: str = "mm") -> str:
    """The Anipose ``calibration.toml`` text: ``[cam_N]`` tables only, translations in ``units``."""
    if units not in UNIT_SCALE_TO_MM:
        raise CalibrationFormatError(
            f"units must be one of {sorted(UNIT_SCALE_TO_MM)}, got {units!r}"
        )
    scale = UNIT_SCALE_TO_MM[units]
    data = rig_to_toml_dict(rig)
    data.pop("metadata", None)
    for i, cam in enumerate(rig):
        data[f"cam_{i}"]["translation"] = (cam.t / scale).tolist()
    return tomli_w.dumps(data)


def write_anipose_calibration(rig: CameraRig, path: str | Path, units: str = "mm") -> None:
    """Write an Anipose ``calibration.toml`` (no FreiPose metadata; translations in ``units``)."""
    atomic_write_text(path, anipose_toml_text(rig, units))


# -- JARVIS (OpenCV FileStorage YAML, one file per camera) -------------------------------
# JARVIS's camera entries; E and F (from its stereo step) and the image size are allowed.
_JARVIS_KEYS = ("intrinsicMatrix", "distortionCoefficients", "R", "T")


def _read_jarvis_file(path: Path) -> tuple[str, dict[str, Any]]:
    import cv2

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise CalibrationFormatError(
            f"{path}: not an OpenCV FileStorage YAML file ({exc})"
        ) from exc
    if not fs.isOpened():
        raise CalibrationFormatError(f"{path}: OpenCV cannot open this file as FileStorage YAML")
    try:
        return path.stem, _jarvis_values(fs, path)
    except cv2.error as exc:
        raise CalibrationFormatError(f"{path}: malformed OpenCV FileStorage entry ({exc})") from exc
    finally:
        fs.release()


def _jarvis_values(fs: Any, path: Path) -> dict[str, Any]:
    """The camera entries of an open FileStorage (K, R still transposed as stored)."""
    vals: dict[str, Any] = {}
    for key in _JARVIS_KEYS:
        node = fs.getNode(key)
        mat = None if node.empty() else node.mat()
        if mat is None:
            raise CalibrationFormatError(
                f"{path}: missing {key!r}; a JARVIS camera file holds intrinsicMatrix (K "
                f"transposed), distortionCoefficients, R (transposed) and T (mm)"
            )
        vals[key] = np.asarray(mat, dtype=np.float64)
    known = (*_JARVIS_KEYS, "E", "F", "image_width", "image_height", "imageSize")
    check_keys(dict.fromkeys(fs.root().keys()), known, str(path), CalibrationFormatError)
    size: tuple[int, ...] | None = None
    w, h = fs.getNode("image_width"), fs.getNode("image_height")
    if not w.empty() and not h.empty():
        size = (int(w.real()), int(h.real()))
    elif not fs.getNode("imageSize").empty():  # cv::Size as written by OpenCV: [w, h]
        node = fs.getNode("imageSize")
        arr = node.mat() if node.isMap() else [node.at(i).real() for i in range(node.size())]
        size = tuple(int(v) for v in np.asarray(arr).ravel()[:2])
    vals["size"] = size
    return vals


def _jarvis_files(path: Path) -> list[Path]:
    if path.is_dir():
        files = [
            p
            for p in path.iterdir()
            if p.suffix.lower() in _YAML_SUFFIXES and not p.name.startswith(".")
        ]
        if not files:
            raise CalibrationFormatError(
                f"{path}: the folder holds no camera files (<camera>.yaml); a JARVIS calibration "
                f"is a folder with one OpenCV YAML file per camera"
            )
        return sorted(files, key=lambda p: natural_key(p.stem))
    return [path]


def read_jarvis_calibration(path: str | Path) -> CameraRig:
    """Read a JARVIS calibration: a folder of ``<camera>.yaml`` files, or one such file."""
    path = Path(path)
    entries = [_read_jarvis_file(p) for p in _jarvis_files(path)]
    names = [n for n, _ in entries]
    Ks = [v["intrinsicMatrix"].reshape(3, 3).T for _, v in entries]
    stored = {n: v["size"] for n, v in entries}
    sizes, estimated = _fill_sizes(path, names, Ks, stored)
    cams = []
    for (n, v), K, size in zip(entries, Ks, sizes):
        R = as_rotation(v["R"].reshape(3, 3).T, str(path), n)
        cams.append(
            _make_camera(
                str(path),
                n,
                size=size,
                K=K,
                dist=v["distortionCoefficients"].ravel(),
                R=R,
                t=v["T"].ravel(),
            )
        )
    return CameraRig(tuple(cams), _metadata({}, estimated, source_format="JARVIS YAML"))


def _opencv_matrix(name: str, a: np.ndarray) -> str:
    """One ``!!opencv-matrix`` entry of doubles (repr precision, so reading back is exact)."""
    a = np.asarray(a, dtype=np.float64)
    data = ", ".join(repr(float(v)) for v in a.ravel())
    return (
        f"{name}: !!opencv-matrix\n   rows: {a.shape[0]}\n   cols: {a.shape[1]}\n   dt: d\n"
        f"   data: [ {data} ]\n"
    )


def jarvis_yaml_text(cam: Camera) -> str:
    """The OpenCV FileStorage YAML of one camera as JARVIS writes it (K and R transposed).

    ``image_width``/``image_height`` are FreiPose extras that JARVIS ignores.
    """
    return (
        "%YAML:1.0\n---\n"
        + _opencv_matrix("intrinsicMatrix", cam.K.T)
        + _opencv_matrix("distortionCoefficients", cam.dist.reshape(1, 5))
        + _opencv_matrix("R", cam.R.T)
        + _opencv_matrix("T", cam.t.reshape(3, 1))
        + f"image_width: {int(cam.size[0])}\nimage_height: {int(cam.size[1])}\n"
    )


def _write_jarvis_file(cam: Camera, path: Path) -> None:
    atomic_write_text(path, jarvis_yaml_text(cam))


def write_jarvis_calibration(rig: CameraRig, path: str | Path) -> None:
    """Write a JARVIS calibration folder with one ``<camera>.yaml`` per camera.

    ``path`` is the folder (created if needed). A path ending in ``.yaml``/``.yml`` writes
    that single file, which needs a one-camera rig. Existing files of *other* cameras in
    the folder are an error (they would be read back as extra cameras).
    """
    path = Path(path)
    if path.suffix.lower() in _YAML_SUFFIXES and not path.is_dir():
        if len(rig) != 1:
            raise CalibrationFormatError(
                f"{path}: a JARVIS YAML file holds one camera, the rig has {len(rig)}; give a "
                f"folder as output (e.g. calib_jarvis/ with --format jarvis)"
            )
        _write_jarvis_file(rig[0], path)
        return
    if path.exists() and not path.is_dir():
        raise CalibrationFormatError(
            f"{path}: exists and is not a folder; JARVIS calibrations are folders"
        )
    path.mkdir(parents=True, exist_ok=True)
    others = sorted(
        p.name
        for p in path.iterdir()
        if p.suffix.lower() in _YAML_SUFFIXES
        and not p.name.startswith(".")
        and p.stem not in rig.names
    )
    if others:
        raise CalibrationFormatError(
            f"{path}: the folder already holds camera files {others} that are not in this rig; "
            f"they would be read as extra cameras. Write to an empty folder."
        )
    for cam in rig:
        _write_jarvis_file(cam, path / f"{cam.name}.yaml")


# -- DANNCE label3d_dannce.mat ---------------------------------------------------------
def dannce_camera_params(
    params: Mapping[str, Any], name: str, source: str = "<dannce>"
) -> dict[str, np.ndarray]:
    """OpenCV-convention ``K``, ``dist``, ``R``, ``t`` from one DANNCE ``params`` struct.

    DANNCE uses MATLAB's row-vector convention: ``x_cam = X @ r + t`` and
    ``[u v 1] ∝ [xd yd 1] @ K``, so ``K`` and ``r`` are the transposes of OpenCV's.
    """
    missing = [k for k in ("K", "r", "t") if k not in params]
    if missing:
        raise CalibrationFormatError(
            f"{source}: camera {name!r} params lack {missing}; DANNCE params need K, "
            f"RDistort, TDistort, r and t"
        )
    where = f"{source}: camera {name!r} params"
    check_keys(params, ("K", "RDistort", "TDistort", "r", "t"), where, CalibrationFormatError)
    K = np.asarray(params["K"], dtype=np.float64).reshape(3, 3).T
    rd = np.asarray(params.get("RDistort", np.zeros(3)), dtype=np.float64).ravel()
    td = np.asarray(params.get("TDistort", np.zeros(2)), dtype=np.float64).ravel()
    if rd.size > 3 or td.size > 2:
        raise CalibrationFormatError(
            f"{source}: camera {name!r}: RDistort must have up to 3 and TDistort up to 2 values, "
            f"got {rd.size} and {td.size}"
        )
    rd = np.pad(rd, (0, 3 - rd.size))
    td = np.pad(td, (0, 2 - td.size))
    dist = np.array([rd[0], rd[1], td[0], td[1], rd[2]])
    R = as_rotation(np.asarray(params["r"], dtype=np.float64).reshape(3, 3).T, source, name)
    t = np.asarray(params["t"], dtype=np.float64).ravel()
    return {"K": K, "dist": dist, "R": R, "t": t}


def read_dannce_calibration(path: str | Path) -> CameraRig:
    """Read the cameras of a DANNCE/Label3D ``*.mat`` file (``params`` and ``camnames``); mm."""
    from freipose.io.matlab import load_mat

    path = Path(path)
    mat = load_mat(path)
    if "params" not in mat:
        raise CalibrationFormatError(
            f"{path}: no 'params' variable; a DANNCE label3d file holds params (one struct per "
            f"camera with K, RDistort, TDistort, r, t); variables found: {sorted(mat)}"
        )
    params = mat["params"]
    params = [params] if isinstance(params, dict) else list(params)
    if not params or not all(isinstance(p, dict) for p in params):
        raise CalibrationFormatError(f"{path}: 'params' must be a cell array of structs")
    names = mat.get("camnames")
    if isinstance(names, str):
        names = [names]
    if names is None:
        names = [f"Camera{i + 1}" for i in range(len(params))]
    names = [str(n) for n in names]
    if len(names) != len(params):
        raise CalibrationFormatError(
            f"{path}: {len(names)} camnames for {len(params)} camera params"
        )
    cps = [dannce_camera_params(p, n, str(path)) for p, n in zip(params, names)]
    sizes, estimated = _fill_sizes(path, names, [c["K"] for c in cps], {})
    cams = [_make_camera(str(path), n, size=s, **c) for n, s, c in zip(names, sizes, cps)]
    return CameraRig(tuple(cams), _metadata({}, estimated, source_format="DANNCE label3d .mat"))


def with_image_sizes(rig: CameraRig, sizes: Mapping[str | None, tuple[int, int]]) -> CameraRig:
    """Set image sizes: key ``None`` applies to every camera, a camera name to that one."""
    unknown = [n for n in sizes if n is not None and n not in rig.names]
    if unknown:
        raise UnknownCameraError(f"no cameras named {unknown} in the rig; cameras are {rig.names}")
    cams = []
    for c in rig:
        s = sizes.get(c.name, sizes.get(None))
        cams.append(c if s is None else c.replace(size=tuple(s)))
    md = dict(rig.metadata)
    left = [n for n in md.get(ESTIMATED_KEY, []) if sizes.get(n, sizes.get(None)) is None]
    if left:
        md[ESTIMATED_KEY] = left
    else:
        md.pop(ESTIMATED_KEY, None)
    return CameraRig(tuple(cams), md)


# Format name -> reader / writer, and suffix (lower case) -> format name ("/": a folder).
READERS: Mapping[str, Callable[[Path], CameraRig]] = MappingProxyType(
    {
        "mjson": read_mjson,
        "anipose": read_anipose_calibration,
        "jarvis": read_jarvis_calibration,
        "dannce": read_dannce_calibration,
    }
)
WRITERS: Mapping[str, Callable[[CameraRig, Path], None]] = MappingProxyType(
    {
        "mjson": write_mjson,
        "anipose": write_anipose_calibration,
        "jarvis": write_jarvis_calibration,
    }
)
SUFFIXES: Mapping[str, str] = MappingProxyType(
    {".json": "mjson", ".yaml": "jarvis", ".yml": "jarvis", ".mat": "dannce", "/": "jarvis"}
)

__all__ = [
    "ESTIMATED_KEY",
    "anipose_toml_text",
    "dannce_camera_params",
    "estimate_size_from_principal_point",
    "jarvis_yaml_text",
    "read_anipose_calibration",
    "read_dannce_calibration",
    "read_jarvis_calibration",
    "read_mjson",
    "video_sizes",
    "with_image_sizes",
    "write_anipose_calibration",
    "write_jarvis_calibration",
    "write_mjson",
]
