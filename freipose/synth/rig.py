"""The synthetic arena and camera rigs: :class:`ArenaConfig`, :func:`default_rig`, rig files.

World frame: millimetres, z up, origin at the centre of the arena floor, floor z = 0; the
arena is an open box of inner size ``size`` (x, y) with walls of ``wall_height``.

Rig file (TOML), documented in ``docs/formats.md`` (see ``examples/rig.toml``)::

    [arena]                         # optional
    size = [600.0, 600.0]           # inner width (x) and depth (y), mm
    wall_height = 100.0             # mm

    [defaults]                      # optional; values every camera inherits
    size = [640, 512]               # width, height in pixels
    focal = "auto"                  # px, or "auto": the arena just fits the image
    distortion = [-0.08, 0.02, 0.0, 0.0, 0.0]

    [[camera]]
    name = "cam0"
    position = [700.0, 0.0, 650.0]  # mm
    look_at = [0.0, 0.0, 30.0]      # mm
    # size, focal, distortion as in [defaults]; optional: fov_deg (horizontal field of view,
    # instead of focal), principal_point = [cx, cy], up = [0, 0, 1], grayscale = true (a
    # monochrome camera, see grayscale_cameras)
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, overload

import numpy as np

from freipose.geometry import Camera, CameraRig
from freipose.io.calibration_world import WorldUp
from freipose.io.toml import check_keys, read_toml
from freipose.synth.errors import RigFileError, SynthError

LAYOUTS = ("ring", "above", "side", "below", "arc")  # the camera layouts of default_rig


@dataclass(frozen=True)
class ArenaConfig:
    """An open-field box: inner ``size`` (x, y) mm centred on the origin, ``wall_height`` mm."""

    size: tuple[float, float] = (600.0, 600.0)
    wall_height: float = 100.0

    def __post_init__(self) -> None:
        try:
            w, d = (float(v) for v in self.size)
        except (TypeError, ValueError):
            raise SynthError(
                f"arena size must be [width, depth] in mm, got {self.size!r}"
            ) from None
        if not (w >= 150 and d >= 150):
            raise SynthError(
                f"arena size must be at least 150 x 150 mm (300 x 300 for a rat), got {w} x {d}"
            )
        if not (0 <= float(self.wall_height) <= 2000):
            raise SynthError(f"arena wall_height must be in [0, 2000] mm, got {self.wall_height}")
        object.__setattr__(self, "size", (w, d))
        object.__setattr__(self, "wall_height", float(self.wall_height))

    @property
    def half(self) -> np.ndarray:
        """(2,) half inner size (x, y), mm."""
        return np.asarray(self.size) / 2

    def corners(self, z: float = 0.0) -> np.ndarray:
        """(4, 3) floor corners of the arena at height z."""
        hx, hy = self.half
        return np.array([[-hx, -hy, z], [hx, -hy, z], [hx, hy, z], [-hx, hy, z]])


def _fit_focal(
    position: np.ndarray,
    target: np.ndarray,
    size: tuple[int, int],
    up: Any,
    arena: ArenaConfig,
    fill: float = 0.92,
) -> float:
    """Focal length (px) at which the arena floor and wall tops just fit into the image."""
    probe = Camera.look_at("probe", position, target, size, 1.0, up=up)
    pts = np.concatenate([arena.corners(0.0), arena.corners(arena.wall_height)])
    xc = pts @ probe.R.T + probe.t
    if np.any(xc[:, 2] <= 1e-6):
        raise SynthError("the arena is partly behind the camera; move it or aim it at the arena")
    xy = np.abs(xc[:, :2] / xc[:, 2:3])
    w, h = size
    return float(min(fill * (w / 2) / xy[:, 0].max(), fill * (h / 2) / xy[:, 1].max()))


FISHEYE_SHAPE = (-0.25, 0.05)  # a, b of the "fisheye" lens: r_d = r (1 + a s² + b s⁴)
FISHEYE_ZOOM = 1.08  # focal factor of the fisheye lens (its strong barrel shrinks the arena)


def _lens(
    lens: str, rng: np.random.Generator | None, focal: float, size: tuple[int, int]
) -> tuple[list[float] | None, float]:
    """Distortion (k1, k2, p1, p2, k3) of a ``lens`` and the zoom that keeps the arena framed.

    Barrel distortion shrinks the image towards the corners; the zoom factor on the focal
    length compensates part of that. The fisheye's radial map is
    ``r_d = r (1 + a s² + b s⁴)`` with ``s = r / R`` (``R`` the image corner's normalized
    radius) and ``b >= 0.8 a²``: it rises everywhere (never folds), and the image corner
    sees about 45 % further out than a pinhole would.
    """
    if lens == "pinhole":
        return None, 1.0
    if lens == "fisheye":
        a, b = FISHEYE_SHAPE
        if rng is not None:
            a *= float(rng.uniform(0.85, 1.15))
            b = max(b, 0.8 * a * a)
        corner = math.hypot(size[0] / 2, size[1] / 2) / (focal * FISHEYE_ZOOM)
        p = (0.0, 0.0) if rng is None else tuple(float(v) for v in rng.normal(size=2) * 5e-4)
        return [a / corner**2, b / corner**4, p[0], p[1], 0.0], FISHEYE_ZOOM
    k1 = -0.08 if rng is None else float(rng.uniform(-0.14, -0.03))
    k2 = 0.02 if rng is None else float(rng.uniform(0.0, 0.04))
    p = (0.0, 0.0) if rng is None else tuple(float(v) for v in rng.normal(size=2) * 5e-4)
    return [k1, k2, p[0], p[1], 0.0], 1.0 - 0.2 * k1  # zoom in a bit


def _placement_of(
    i: int, n: int, layout: str, reach: float, rng: np.random.Generator | None
) -> tuple[np.ndarray, np.ndarray, tuple[float, float, float]]:
    """(position, aim point, up) of camera ``i`` of ``n`` in a layout (see :func:`default_rig`)."""
    top = n >= 5 and layout in ("ring", "above")
    n_ring = n - 1 if top else n
    jitter = rng.normal(size=3) * 25.0 if rng is not None else np.zeros(3)
    aim = rng.normal(size=3) * [15.0, 15.0, 5.0] if rng is not None else np.zeros(3)
    if top and i == n - 1:
        pos = np.array([0.0, -180.0 * reach, 1250.0 * reach]) + jitter
        return pos, np.array([0.0, 0.0, 0.0]) + aim, (0.0, 1.0, 0.0)
    az = 2 * math.pi * i / n_ring + math.radians(20)
    if layout == "arc":  # one side of the arena only: a 150 degree arc
        az = math.radians(150.0 * (i / max(n - 1, 1) - 0.5))
    radius, height = {
        "ring": (720.0, 620.0) if i % 2 == 0 else (640.0, 820.0),
        "above": (380.0, 1050.0) if i % 2 == 0 else (320.0, 1150.0),
        "side": (780.0, 380.0) if i % 2 == 0 else (720.0, 460.0),
        "arc": (720.0, 480.0) if i % 2 == 0 else (640.0, 700.0),
    }[layout]
    radius, height = radius * reach, height * reach
    pos = np.array([radius * math.cos(az), radius * math.sin(az), height]) + jitter
    return pos, np.array([0.0, 0.0, 30.0]) + aim, (0.0, 0.0, 1.0)


def default_rig(
    n_cameras: int = 7,
    size: tuple[int, int] = (320, 256),
    seed: int | None = None,
    arena: ArenaConfig | None = None,
    distortion: bool = True,
    lens: str = "standard",
    layout: str = "ring",
) -> CameraRig:
    """N cameras placed like a lab rig around and above the arena, all looking at its centre.

    Layouts: ``"ring"``: with 5 or more cameras one looks down from the ceiling and the
    others stand on a ring (alternately higher and lower); fewer cameras all stand on the
    ring. ``"above"``: the ring high above the arena, looking down steeply. ``"side"``: low
    cameras looking over the walls. ``"below"``: the ``"ring"`` of N - 1 cameras and a last
    one under a transparent floor (:func:`camera_below_floor`). ``"arc"``: all cameras on
    one side of the arena, spread over 150 degrees, alternately low and high (a rig against
    a wall; domain randomisation never draws it). Focal lengths are chosen so
    that the arena fills the image. ``seed`` jitters positions, aim points, focal lengths,
    principal points and distortion (None: the nominal rig).

    Args:
        n_cameras: number of cameras (1..32), named ``cam0``... .
        size: image size (width, height) of every camera.
        seed: jitter seed, or None.
        arena: the arena (default :class:`ArenaConfig`).
        distortion: give the lenses distortion (False: pinhole, whatever ``lens``).
        lens: ``"standard"`` (mild barrel distortion), ``"fisheye"`` (strong radial
            distortion scaled to the field of view, :data:`FISHEYE_SHAPE`, rising to the
            image corners and beyond) or ``"pinhole"``.
        layout: ``"ring"``, ``"above"``, ``"side"``, ``"below"`` or ``"arc"``.

    Returns:
        :class:`CameraRig` with metadata describing the world frame.
    """
    if not 1 <= int(n_cameras) <= 32:
        raise SynthError(f"n_cameras must be in 1..32, got {n_cameras}")
    if layout not in LAYOUTS:
        raise SynthError(f"layout must be one of {', '.join(LAYOUTS)}, got {layout!r}")
    arena = arena or ArenaConfig()
    w, h = (int(v) for v in size)
    if w < 16 or h < 16:
        raise SynthError(f"image size must be at least 16 x 16 px, got {w} x {h}")
    rng = np.random.default_rng(seed) if seed is not None else None
    n = int(n_cameras)
    below = layout == "below" and n >= 2
    reach = float(max(arena.size)) / 600.0
    n_above = n - 1 if below else n
    lens = lens if distortion else "pinhole"
    cams = []
    for i in range(n_above):
        pos, target, up = _placement_of(i, n_above, "ring" if below else layout, reach, rng)
        focal = _fit_focal(pos, target, (w, h), up, arena)
        pp = None
        if rng is not None:
            focal *= float(rng.uniform(0.97, 1.03))
            pp = ((w - 1) / 2 + rng.normal() * 0.01 * w, (h - 1) / 2 + rng.normal() * 0.01 * h)
        dist, zoom = _lens(lens, rng, focal, (w, h))
        cams.append(
            Camera.look_at(
                f"cam{i}",
                pos,
                target,
                (w, h),
                focal * zoom,
                up=up,
                dist=dist,
                principal_point=pp,
            )  # fmt: skip
        )
    if below:
        cams.append(camera_below_floor(f"cam{n - 1}", (w, h), arena, lens != "pinhole"))
    return CameraRig(tuple(cams), _metadata(arena))


def camera_below_floor(
    name: str, size: tuple[int, int], arena: ArenaConfig | None = None, distortion: bool = True
) -> Camera:
    """A camera under a transparent floor, looking up at the arena's centre.

    It stands 650 mm below the centre (scaled with the arena), a little off to one side, its
    image's up along world +y. Its focal length frames the region that the synthetic
    calibration board moves through (:func:`freipose.synth.board.board_poses`: 260 mm around
    the centre at its lowest height, 140 mm), so that the board covers the image as it does in
    the other cameras; the renderer sees the board through the floor.

    Args:
        name: the camera's name.
        size: image size (width, height).
        arena: the arena (default :class:`ArenaConfig`).
        distortion: give the lens the mild barrel distortion of :func:`default_rig`.

    Returns:
        the camera.
    """
    arena = arena or ArenaConfig()
    reach = float(max(arena.size)) / 600.0
    pos = np.array([60.0 * reach, -80.0 * reach, -650.0 * reach])
    target = np.array([0.0, 0.0, 200.0 * reach])
    up = (0.0, 1.0, 0.0)
    w, h = (int(v) for v in size)
    probe = Camera.look_at("probe", pos, target, (w, h), 1.0, up=up)
    box = np.array([[x, y, 140.0] for x in (-260.0, 260.0) for y in (-260.0, 260.0)]) * reach
    xc = box @ probe.R.T + probe.t
    xy = np.abs(xc[:, :2] / xc[:, 2:3])
    focal = float(min(0.92 * (w / 2) / xy[:, 0].max(), 0.92 * (h / 2) / xy[:, 1].max()))
    dist = [-0.08, 0.02, 0.0, 0.0, 0.0] if distortion else None
    if distortion:
        focal *= 1.0 + 0.2 * 0.08
    return Camera.look_at(name, pos, target, (w, h), focal, up=up, dist=dist)


def _metadata(arena: ArenaConfig) -> dict[str, Any]:
    """The rig's metadata: the synthetic world's up (z) and floor (z = 0) and the arena."""
    truth = WorldUp(np.array([0.0, 0.0, 1.0]), "the synthetic scene's truth", 0.0)
    return {
        "units": "mm",
        "world": "synthetic scene: origin at the arena floor centre, z up, floor z = 0",
        "arena_size": list(arena.size),
        "arena_wall_height": arena.wall_height,
        **truth.metadata(),
    }


_CAMERA_KEYS = frozenset({"name", "position", "look_at", "size", "focal", "fov_deg", "distortion",
                          "principal_point", "up", "grayscale"})  # fmt: skip
_DEFAULT_KEYS = _CAMERA_KEYS - {"name", "position", "look_at"}
_TOP_KEYS = frozenset({"arena", "defaults", "camera"})


def _vec(value: Any, n: int, what: str, where: str, src: str) -> np.ndarray:
    """``value`` as (n,) finite floats.

    Raises:
        RigFileError: not a list of ``n`` finite numbers.
    """
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise RigFileError(f"{src}: {where}: {what} must be a list of {n} numbers, got {value!r}")
    return arr


def _table(data: Mapping[str, Any], key: str, known: frozenset[str], src: str) -> Mapping[str, Any]:
    """The optional table ``[key]`` of the rig file (empty when absent), its keys checked.

    Raises:
        RigFileError: not a table, or a key outside ``known``.
    """
    table = data.get(key, {})
    if not isinstance(table, Mapping):
        raise RigFileError(f"{src}: [{key}] must be a table")
    check_keys(table, known, f"{src}: [{key}]", RigFileError)
    return table


def _arena_of(table: Mapping[str, Any], src: str) -> ArenaConfig:
    """The arena of the ``[arena]`` table (defaults: 600 x 600 mm, walls 100 mm)."""
    try:
        return ArenaConfig(
            tuple(_vec(table.get("size", (600.0, 600.0)), 2, "size", "[arena]", src)),
            float(table.get("wall_height", 100.0)),
        )
    except (TypeError, ValueError) as exc:
        raise RigFileError(f"{src}: [arena]: {exc}") from None


@dataclass(frozen=True, eq=False)
class _Placement:
    """Where a camera stands and looks (mm): ``position``, ``look_at`` and ``up``, each (3,)."""

    position: np.ndarray
    look_at: np.ndarray
    up: np.ndarray


def _placement(e: Mapping[str, Any], where: str, src: str) -> _Placement:
    """The position, aim point and up vector of the camera entry ``e``.

    Raises:
        RigFileError: malformed vectors, aim point at the position, position below the floor,
            or ``up`` along the viewing direction.
    """
    pos = _vec(e["position"], 3, "position", where, src)
    target = _vec(e["look_at"], 3, "look_at", where, src)
    up = _vec(e.get("up", (0.0, 0.0, 1.0)), 3, "up", where, src)
    if np.linalg.norm(target - pos) < 1.0:
        raise RigFileError(f"{src}: {where}: position and look_at coincide")
    if pos[2] <= 0:
        raise RigFileError(
            f"{src}: {where}: position z = {pos[2]} is at or below the floor (z = 0); "
            "cameras must be above it"
        )
    if np.linalg.norm(np.cross(target - pos, up)) < 1e-6 * np.linalg.norm(target - pos):
        raise RigFileError(
            f"{src}: {where}: the camera looks straight along 'up'; set up = [0, 1, 0]"
        )
    return _Placement(pos, target, up)


def _image_size(
    e: Mapping[str, Any], default_size: tuple[int, int] | None, where: str, src: str
) -> tuple[int, int]:
    """The image size (width, height) of the camera entry ``e`` (or ``default_size``)."""
    size_v = e.get("size", default_size)
    if size_v is None:
        raise RigFileError(
            f"{src}: {where} has no size; set size = [width, height] (or in [defaults])"
        )
    sz = _vec(size_v, 2, "size", where, src)
    if np.any(sz != np.round(sz)) or np.any(sz < 16):
        raise RigFileError(f"{src}: {where}: size must be two integers >= 16, got {size_v!r}")
    return int(sz[0]), int(sz[1])


def _focal(
    entry: Mapping[str, Any],
    defaults: Mapping[str, Any],
    size: tuple[int, int],
    place: _Placement,
    arena: ArenaConfig,
    where: str,
    src: str,
) -> float:
    """The focal length (px) of a camera: ``fov_deg``, ``focal`` or ``"auto"`` (fit the arena).

    The camera's own ``focal`` or ``fov_deg`` wins over the one in ``[defaults]``.
    """
    e = {**defaults, **entry}
    if "focal" in entry and "fov_deg" in entry:
        raise RigFileError(f"{src}: {where}: give focal or fov_deg, not both")
    if "fov_deg" in entry or ("fov_deg" in defaults and "focal" not in entry):
        fov = e["fov_deg"]
        if not isinstance(fov, (int, float)) or not 1 <= fov <= 170:
            raise RigFileError(f"{src}: {where}: fov_deg must be a number in [1, 170], got {fov!r}")
        return (size[0] / 2) / math.tan(math.radians(fov) / 2)
    focal_v = e.get("focal", "auto")
    if focal_v == "auto":
        try:
            return _fit_focal(place.position, place.look_at, size, place.up, arena)
        except ValueError as exc:
            raise RigFileError(f"{src}: {where}: focal = 'auto': {exc}") from None
    if isinstance(focal_v, (int, float)) and not isinstance(focal_v, bool) and focal_v > 0:
        return float(focal_v)
    raise RigFileError(
        f"{src}: {where}: focal must be a positive number of pixels or 'auto', got {focal_v!r}"
    )


def _camera_name(e: Mapping[str, Any], names: set[str], where: str, src: str) -> str:
    """The camera's name, checked: non-empty, no spaces or slashes, not in ``names``."""
    name = e["name"]
    if not isinstance(name, str) or not name or any(c in name for c in "/\\ "):
        raise RigFileError(
            f"{src}: {where}: name must be a non-empty string without spaces or slashes"
        )
    if name in names:
        raise RigFileError(f"{src}: camera name {name!r} is used twice; names must be unique")
    return name


def _camera(
    entry: Mapping[str, Any],
    where: str,
    defaults: Mapping[str, Any],
    names: set[str],
    default_size: tuple[int, int] | None,
    arena: ArenaConfig,
    src: str,
) -> Camera:
    """The camera of one ``[[camera]]`` entry (``defaults`` fill in what it does not give).

    Raises:
        RigFileError: an unknown key, a missing name/position/look_at, a name used before
            (in ``names``) or any malformed value; the message names the entry.
    """
    check_keys(entry, _CAMERA_KEYS, f"{src}: {where}", RigFileError)
    e = {**defaults, **entry}
    for req in ("name", "position", "look_at"):
        if req not in e:
            raise RigFileError(
                f"{src}: {where} has no {req!r}; every camera needs name, position and look_at"
            )
    name = _camera_name(e, names, where, src)
    names.add(name)
    place = _placement(e, where, src)
    size = _image_size(e, default_size, where, src)
    focal = _focal(entry, defaults, size, place, arena, where, src)
    dist = _vec(
        e.get("distortion", (0, 0, 0, 0, 0)), 5, "distortion (k1, k2, p1, p2, k3)", where, src
    )
    if np.any(np.abs(dist) > 2):
        raise RigFileError(
            f"{src}: {where}: distortion coefficients beyond +-2 are not plausible: {dist.tolist()}"
        )
    pp = None
    if "principal_point" in e:
        pp = tuple(_vec(e["principal_point"], 2, "principal_point", where, src))
    try:
        cam = Camera.look_at(
            name, place.position, place.look_at, size, focal, up=place.up, dist=dist,
            principal_point=pp,
        )  # fmt: skip
    except ValueError as exc:
        raise RigFileError(f"{src}: {where}: {exc}") from None
    xc = cam.R @ np.array([0.0, 0.0, 0.0]) + cam.t
    if xc[2] <= 0:
        raise RigFileError(
            f"{src}: {where}: the arena centre is behind the camera; aim look_at at the arena"
        )
    return cam


def rig_from_dict(
    data: Mapping[str, Any], source: str = "<rig>", default_size: tuple[int, int] | None = None
) -> tuple[CameraRig, ArenaConfig]:
    """Build the rig and arena from a parsed rig file (see the module docstring).

    Args:
        data: the parsed file.
        source: where ``data`` comes from (the file), for messages.
        default_size: image size for cameras that give none (neither they nor [defaults]).

    Returns:
        ``(rig, arena)``.

    Raises:
        RigFileError: malformed content (the message names the entry and the fix).
    """
    src = source
    check_keys(data, _TOP_KEYS, f"{src}: the top level", RigFileError)
    arena = _arena_of(_table(data, "arena", frozenset({"size", "wall_height"}), src), src)
    defaults = _table(data, "defaults", _DEFAULT_KEYS, src)
    entries = data.get("camera")
    if not entries or not isinstance(entries, list):
        raise RigFileError(
            f"{src}: no cameras; add one [[camera]] table per camera "
            "with name, position and look_at"
        )
    cams = []
    names: set[str] = set()
    for i, entry in enumerate(entries):
        if not isinstance(entry, Mapping):
            raise RigFileError(f"{src}: camera #{i + 1} must be a table")
        where = f"camera #{i + 1} ({entry.get('name', 'unnamed')!r})"
        cams.append(_camera(entry, where, defaults, names, default_size, arena, src))
    return CameraRig(tuple(cams), _metadata(arena)), arena


def grayscale_cameras(path: str | Path) -> tuple[str, ...]:
    """The cameras of a rig file with ``grayscale = true`` (own or from ``[defaults]``).

    Raises:
        RigFileError: ``grayscale`` is not true or false.
    """
    data = read_toml(path, "rig file", RigFileError)
    defaults = data.get("defaults", {})
    default = defaults.get("grayscale", False) if isinstance(defaults, Mapping) else False
    out = []
    for e in data.get("camera", []) or []:
        gray = e.get("grayscale", default) if isinstance(e, Mapping) else False
        if not isinstance(gray, bool):
            raise RigFileError(f"{path}: camera {e.get('name')!r}: grayscale must be true or false")
        if gray:
            out.append(str(e["name"]))
    return tuple(out)


@overload
def load_rig_file(
    path: str | Path, default_size: tuple[int, int] | None = None, with_arena: Literal[False] = ...
) -> CameraRig: ...


@overload
def load_rig_file(
    path: str | Path, default_size: tuple[int, int] | None = None, *, with_arena: Literal[True]
) -> tuple[CameraRig, ArenaConfig]: ...


def load_rig_file(
    path: str | Path, default_size: tuple[int, int] | None = None, with_arena: bool = False
) -> CameraRig | tuple[CameraRig, ArenaConfig]:
    """Read a rig TOML file (format in the module docstring) into a :class:`CameraRig`.

    Args:
        path: the file.
        default_size: image size for cameras that give none (neither they nor [defaults]).
        with_arena: also return the file's :class:`ArenaConfig`.

    Returns:
        The rig, or ``(rig, arena)`` with ``with_arena``.

    Raises:
        InputFileError: no such file (a ``FileNotFoundError``).
        RigFileError: not TOML or malformed content (the message names the entry and the fix).
    """
    data = read_toml(path, "rig file", RigFileError)
    rig, arena = rig_from_dict(data, str(path), default_size)
    return (rig, arena) if with_arena else rig
