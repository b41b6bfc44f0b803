"""Behavioral-variables file ``VARS.h5`` (schema in ``docs/formats.md``) and poses -> variables.

``values`` float32 (T, V); ``names``, ``types``, ``kinds``, ``components``, ``parts`` (V,)
UTF-8; ``involved`` bool (V, K); ``keypoints`` (K,); ``frame_index`` (T,) int64;
``frequencies`` (F,) Hz; root attributes ``fps``, ``up``, ``floor_normal``,
``floor_offset``, ``floor_source``, ``settings`` (JSON), ``info`` (JSON), ``source``,
``source_stamp``, ``freipose_version``, ``schema = "freipose.variables"``, ``schema_version``.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from freipose import __version__
from freipose.analysis.floor import FloorPlane, resolve_floor
from freipose.analysis.variables import (
    VariableConfig,
    Variables,
    check_keypoints,
    compute_variables,
)
from freipose.errors import FreiPoseError, InputFileError
from freipose.io.atomic import atomic_h5
from freipose.io.calibration_world import world_up
from freipose.io.poses import PoseData, read_poses_h5
from freipose.skeleton import Skeleton, load_skeleton

log = logging.getLogger(__name__)

SCHEMA = "freipose.variables"
SCHEMA_VERSION = 1


class VariablesFormatError(FreiPoseError):
    """A variables file is malformed; the message names the file and the problem."""


def _strs(values: Any) -> np.ndarray:
    return np.array([str(v) for v in values], dtype=h5py.string_dtype("utf-8"))


def _decode(arr: np.ndarray) -> tuple[str, ...]:
    return tuple(s.decode() if isinstance(s, bytes) else str(s) for s in arr)


def source_stamp(path: str | Path) -> str:
    """Size and modification time of a file, to tell whether a cached result is stale."""
    st = Path(path).stat()
    return f"{st.st_size}:{st.st_mtime_ns}"


def write_variables_h5(
    var: Variables,
    path: str | Path,
    settings: dict[str, Any] | None = None,
    source: str | Path | None = None,
) -> None:
    """Write ``VARS.h5`` atomically.

    Args:
        var: the variables.
        path: the file to write.
        settings: the settings that produced the variables (stored as JSON; used to decide
            whether a cached file can be reused).
        source: the poses file the variables came from.
    """
    t, v = var.values.shape
    with atomic_h5(path) as f:
        f.attrs["schema"] = SCHEMA
        f.attrs["schema_version"] = SCHEMA_VERSION
        f.create_dataset("values", data=var.values, chunks=(min(t, max(1, 2**20 // max(v, 1))), v))
        f.create_dataset("names", data=_strs(var.names))
        f.create_dataset("types", data=_strs(var.types))
        f.create_dataset("kinds", data=_strs(var.kinds))
        f.create_dataset("components", data=_strs(var.components))
        f.create_dataset("parts", data=_strs(var.parts))
        f.create_dataset("involved", data=var.involved)
        f.create_dataset("keypoints", data=_strs(var.keypoints))
        f.create_dataset("frame_index", data=var.frame_index)
        f.create_dataset("frequencies", data=var.frequencies)
        f.attrs["fps"] = var.fps
        f.attrs["up"] = var.floor.normal
        f.attrs["floor_normal"] = var.floor.normal
        f.attrs["floor_offset"] = var.floor.offset
        f.attrs["floor_source"] = var.floor.source
        f.attrs["settings"] = json.dumps(settings or {}, sort_keys=True)
        f.attrs["info"] = json.dumps(dict(var.info), default=str)
        f.attrs["freipose_version"] = __version__
        if source is not None:
            f.attrs["source"] = str(source)
            f.attrs["source_stamp"] = source_stamp(source)


def read_variables_attrs(path: str | Path) -> dict[str, Any]:
    """Root attributes of a ``VARS.h5`` (cheap; used for cache checks)."""
    with h5py.File(path, "r") as f:
        return {k: f.attrs[k] for k in f.attrs}


def read_variables_h5(path: str | Path) -> Variables:
    """Read and validate ``VARS.h5``.

    Raises:
        VariablesFormatError: not a valid variables file (the message says why).
        FileNotFoundError: the file does not exist.
    """
    path = Path(path)
    if not path.exists():
        raise InputFileError(f"variables file not found: {path}")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise VariablesFormatError(f"{path}: not a readable HDF5 file ({exc})") from exc
    with f:
        if f.attrs.get("schema") != SCHEMA:
            raise VariablesFormatError(
                f"{path}: not a FreiPose variables file (schema {f.attrs.get('schema')!r}, "
                f"expected {SCHEMA!r}); make one with 'freipose analyze variables POSES.h5'"
            )
        need = ["values", "names", "kinds", "components", "parts", "involved", "keypoints"]
        need += ["frame_index", "frequencies"]
        missing = [d for d in need if d not in f]
        if missing:
            raise VariablesFormatError(f"{path}: missing datasets {missing}")
        try:
            floor = FloorPlane(
                np.asarray(f.attrs["floor_normal"]),
                float(f.attrs["floor_offset"]),
                str(f.attrs.get("floor_source", "")),
            )
            return Variables(
                values=f["values"][()],
                names=_decode(f["names"][()]),
                kinds=_decode(f["kinds"][()]),
                components=_decode(f["components"][()]),
                parts=_decode(f["parts"][()]),
                involved=f["involved"][()].astype(bool),
                keypoints=_decode(f["keypoints"][()]),
                frame_index=f["frame_index"][()].astype(np.int64),
                fps=float(f.attrs["fps"]),
                frequencies=f["frequencies"][()],
                floor=floor,
                info=json.loads(f.attrs.get("info", "{}")),
            )
        except (KeyError, ValueError) as exc:
            raise VariablesFormatError(f"{path}: {exc}") from exc


def resolve_skeleton(data: PoseData, skeleton: str | Path | Skeleton | None) -> Skeleton:
    """The skeleton for variables: the given one, else the poses file's own, else ``rat``."""
    if isinstance(skeleton, Skeleton):
        skel = skeleton
    elif skeleton is not None:
        skel = load_skeleton(skeleton)
    elif data.skeleton is not None:
        skel = data.skeleton
        if not skel.frame:
            # A skeleton stored without analysis tables: use the shipped one of that name.
            try:
                shipped = load_skeleton(skel.name)
                if shipped.keypoints == skel.keypoints:
                    skel = shipped
            except FileNotFoundError:
                pass
    else:
        skel = load_skeleton("rat")
    return skel


def variables_from_poses(
    data: PoseData,
    skeleton: str | Path | Skeleton | None = None,
    floor: str | Path | FloorPlane = "world",
    config: VariableConfig = VariableConfig(),
    source: str = "poses",
) -> Variables:
    """Behavioral variables of a loaded poses file.

    Args:
        data: the poses (their ``up`` vector defines the default floor).
        skeleton: name, TOML path or Skeleton; default: the poses' own skeleton, else ``rat``.
        floor: ``"world"`` (the floor the poses' calibration stores, else the plane through
            the world origin perpendicular to ``up``), ``"auto"``, a floor TOML path, or a
            plane.
        config: gap filling and STFT settings.
        source: the poses' origin, for messages.

    Returns:
        The variables; poses of several animals give every animal's variables and its social
        variables, each name prefixed with the animal's individual
        (:func:`freipose.analysis.social.recording_variables`).
    """
    skel = resolve_skeleton(data, skeleton)
    check_keypoints(data.keypoints, skel, source)
    feet = data.poses[..., list(skel.feet), :] if skel.feet else None
    known = world_up(data.calibration) if data.calibration is not None else None
    same_up = known is not None and float(known.up @ np.asarray(data.up, np.float64)) > 0.999
    if str(floor) == "world" and known is not None and known.floor is not None and same_up:
        floor = FloorPlane(known.up, known.floor, "calibration")  # the stored floor height
    plane = resolve_floor(floor, data.up, feet)
    if data.individuals is not None:
        from freipose.analysis.social import recording_variables

        if len(data.individuals) == 1:  # one animal with an animal axis: its own variables
            return compute_variables(data.poses[:, 0], data.frame_index, data.fps, skel, plane,
                                     config)  # fmt: skip
        return recording_variables(data.poses, data.individuals, data.frame_index, data.fps,
                                   skel, plane, config)  # fmt: skip
    return compute_variables(data.poses, data.frame_index, data.fps, skel, plane, config)


def variables_settings(
    skeleton: str | Path | Skeleton | None, floor: str | Path | FloorPlane, config: VariableConfig
) -> dict[str, Any]:
    """A JSON-able description of the settings (for cache checks)."""
    if isinstance(skeleton, Skeleton):
        skel_s: Any = skeleton.to_dict()
    else:
        skel_s = None if skeleton is None else str(skeleton)
    if isinstance(floor, FloorPlane):
        floor_s: Any = [floor.normal.tolist(), floor.offset]
    elif str(floor) in ("world", "auto"):
        floor_s = str(floor)
    else:
        floor_s = [str(Path(floor).resolve()), source_stamp(floor)]
    return {
        "skeleton": skel_s,
        "floor": floor_s,
        "max_gap_s": config.max_gap_s,
        "stft_window": config.stft_window,
        "schema_version": SCHEMA_VERSION,
    }


def cached_variables(
    poses_path: str | Path,
    cache_path: str | Path,
    skeleton: str | Path | Skeleton | None = None,
    floor: str | Path | FloorPlane = "world",
    config: VariableConfig = VariableConfig(),
) -> Variables:
    """Variables of a poses file, reusing ``cache_path`` when it is up to date.

    The cache is reused when it was made from the same file with the same settings, so an
    interrupted study analysis resumes where it stopped; else the variables are computed
    and written to ``cache_path``.

    Args:
        poses_path: the poses file.
        cache_path: the cached ``VARS.h5``.
        skeleton: name, TOML path or Skeleton; default: the poses' own skeleton, else ``rat``.
        floor: ``"world"``, ``"auto"``, a floor TOML path, or a plane.
        config: gap filling and STFT settings.

    Returns:
        The variables.
    """
    poses_path, cache_path = Path(poses_path), Path(cache_path)
    settings = variables_settings(skeleton, floor, config)
    if cache_path.is_file():
        try:
            attrs = read_variables_attrs(cache_path)
            if json.loads(attrs.get("settings", "{}")) == json.loads(
                json.dumps(settings)
            ) and attrs.get("source_stamp") == source_stamp(poses_path):
                log.info("reusing variables %s", cache_path)
                return read_variables_h5(cache_path)
        except (OSError, ValueError) as exc:
            log.warning("ignoring unreadable cached variables %s (%s)", cache_path, exc)
    data = read_poses_h5(poses_path, require_up=True)
    var = variables_from_poses(data, skeleton, floor, config, source=str(poses_path))
    write_variables_h5(var, cache_path, settings=settings, source=poses_path)
    return var
