"""``Camera`` and ``CameraRig``: frozen, validated camera models (see package docstring)."""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from freipose._frozen import PicklableFrozen
from freipose.errors import FreiPoseError
from freipose.geometry._checks import check_last
from freipose.geometry.pinhole import project_points
from freipose.geometry.transforms import matrix_to_rodrigues, rodrigues_to_matrix, transform


class CameraError(FreiPoseError):
    """A camera or camera rig with invalid parameters; the message names the camera."""


class UnknownCameraError(CameraError, KeyError):
    """No camera of that name in the rig (also a ``KeyError``, as for a mapping)."""


def _frozen_array(value: Any, shape: tuple[int, ...], what: str, owner: str) -> np.ndarray:
    """Return ``value`` as a read-only float64 array of ``shape`` or raise ``CameraError``."""
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise CameraError(f"camera {owner!r}: {what} must be numeric, got {value!r}") from exc
    if arr.size == int(np.prod(shape)) and arr.shape != shape:
        arr = arr.reshape(shape)
    if arr.shape != shape:
        raise CameraError(
            f"camera {owner!r}: {what} must have shape {shape}, got shape {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise CameraError(f"camera {owner!r}: {what} contains NaN or infinite values")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class Camera:
    """A calibrated pinhole camera with OpenCV distortion.

    Attributes:
        name: camera name (unique within a rig; video file stems use it).
        size: image size ``(width, height)`` in pixels.
        K: intrinsic matrix (3, 3), may carry a skew term ``K[0, 1]``.
        dist: distortion ``(k1, k2, p1, p2, k3)``, shape (5,).
        R: world→camera rotation (3, 3).
        t: world→camera translation (3,) in millimetres.
    """

    name: str
    size: tuple[int, int]
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise CameraError(f"camera name must be a non-empty string, got {self.name!r}")
        try:
            w, h = (int(v) for v in self.size)
        except (TypeError, ValueError) as exc:
            raise CameraError(
                f"camera {self.name!r}: size must be (width, height), got {self.size!r}"
            ) from exc
        if w <= 0 or h <= 0:
            raise CameraError(f"camera {self.name!r}: size must be positive, got {(w, h)}")
        object.__setattr__(self, "size", (w, h))
        K = _frozen_array(self.K, (3, 3), "K", self.name)
        if K[0, 0] <= 0 or K[1, 1] <= 0 or K[1, 0] != 0 or np.any(K[2] != (0, 0, 1)):
            raise CameraError(
                f"camera {self.name!r}: K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] "
                f"with fx, fy > 0, got {K.tolist()}"
            )
        dist = np.zeros(5)
        d = np.asarray(self.dist, dtype=np.float64).ravel()
        if d.size > 5 and np.any(d[5:] != 0):
            raise CameraError(
                f"camera {self.name!r}: only the 5-parameter OpenCV distortion "
                f"(k1, k2, p1, p2, k3) is supported, got {d.size} non-zero terms"
            )
        dist[: min(5, d.size)] = d[:5]
        R = _frozen_array(self.R, (3, 3), "R", self.name)
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise CameraError(f"camera {self.name!r}: R is not a rotation matrix: {R.tolist()}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", _frozen_array(dist, (5,), "dist", self.name))
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", _frozen_array(self.t, (3,), "t", self.name))

    # -- derived quantities -------------------------------------------------------
    @property
    def width(self) -> int:
        """Image width in pixels."""
        return self.size[0]

    @property
    def height(self) -> int:
        """Image height in pixels."""
        return self.size[1]

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world millimetres, shape (3,)."""
        return -self.R.T @ self.t

    @property
    def rvec(self) -> np.ndarray:
        """World→camera rotation as a Rodrigues vector, shape (3,)."""
        return matrix_to_rodrigues(self.R)

    @property
    def extrinsics(self) -> np.ndarray:
        """World→camera 4x4 homogeneous transform."""
        return transform(self.R, self.t)

    @property
    def P(self) -> np.ndarray:
        """Projection matrix ``K [R | t]`` (3, 4), ignoring distortion."""
        return self.K @ np.hstack([self.R, self.t[:, None]])

    @property
    def has_distortion(self) -> bool:
        """Whether any distortion coefficient is non-zero."""
        return bool(np.any(self.dist != 0))

    @classmethod
    def from_rvec(
        cls,
        name: str,
        size: tuple[int, int],
        K: Any,
        dist: Any,
        rvec: Any,
        t: Any,
    ) -> Camera:
        """Build a camera from a Rodrigues rotation vector."""
        return cls(name, size, K, dist, rodrigues_to_matrix(np.asarray(rvec)), t)

    @classmethod
    def look_at(
        cls,
        name: str,
        position: Any,
        target: Any,
        size: tuple[int, int],
        focal: float,
        up: Any = (0.0, 0.0, 1.0),
        dist: Any = None,
        principal_point: Any = None,
    ) -> Camera:
        """A camera at ``position`` (mm) looking at ``target`` with world ``up`` on top."""
        pos = np.asarray(position, dtype=np.float64)
        z = np.asarray(target, dtype=np.float64) - pos
        if np.linalg.norm(z) == 0:
            raise CameraError(f"camera {name!r}: position and look-at target coincide")
        z /= np.linalg.norm(z)
        upv = np.asarray(up, dtype=np.float64)
        x = np.cross(z, upv)
        if np.linalg.norm(x) < 1e-9:  # looking straight along up: pick any x
            x = np.cross(z, np.array([0.0, 1.0, 0.0]))
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        w, h = size
        cx, cy = principal_point if principal_point is not None else ((w - 1) / 2, (h - 1) / 2)
        K = np.array([[focal, 0.0, cx], [0.0, focal, cy], [0.0, 0.0, 1.0]])
        return cls(name, size, K, np.zeros(5) if dist is None else dist, R, -R @ pos)

    def replace(self, **changes: Any) -> Camera:
        """A copy with some fields changed (``name``, ``size``, ``K``, ``dist``, ``R``, ``t``)."""
        kw = {f: getattr(self, f) for f in ("name", "size", "K", "dist", "R", "t")}
        kw.update(changes)
        return Camera(**kw)

    def allclose(self, other: Camera, rtol: float = 1e-9, atol: float = 1e-9) -> bool:
        """True when both cameras have the same name, size and (numerically) parameters."""
        return (
            self.name == other.name
            and self.size == other.size
            and all(
                np.allclose(getattr(self, f), getattr(other, f), rtol=rtol, atol=atol)
                for f in ("K", "dist", "R", "t")
            )
        )

    def __repr__(self) -> str:
        fx, fy = self.K[0, 0], self.K[1, 1]
        c = self.center
        return (
            f"Camera({self.name!r}, size={self.size}, f=({fx:.1f}, {fy:.1f}), "
            f"center=({c[0]:.1f}, {c[1]:.1f}, {c[2]:.1f}) mm)"
        )


@dataclass(frozen=True, eq=False)
class CameraRig(PicklableFrozen):
    """An ordered set of cameras with unique names sharing one world frame.

    Attributes:
        cameras: the cameras, in order (this order is the camera axis of every array).
        metadata: free-form facts about the world frame (units, origin, up vector, ...).
    """

    cameras: tuple[Camera, ...]
    metadata: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        cams = tuple(self.cameras)
        if not cams:
            raise CameraError("a camera rig needs at least one camera, got none")
        for c in cams:
            if not isinstance(c, Camera):
                raise CameraError(f"rig entries must be Camera objects, got {type(c).__name__}")
        names = [c.name for c in cams]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise CameraError(f"camera names in a rig must be unique; repeated: {dupes}")
        object.__setattr__(self, "cameras", cams)
        object.__setattr__(self, "metadata", MappingProxyType(dict(self.metadata)))

    @property
    def names(self) -> list[str]:
        """The camera names, in rig order."""
        return [c.name for c in self.cameras]

    def __len__(self) -> int:
        return len(self.cameras)

    def __iter__(self) -> Iterator[Camera]:
        return iter(self.cameras)

    def __getitem__(self, key: int | str) -> Camera:
        if isinstance(key, str):
            for c in self.cameras:
                if c.name == key:
                    return c
            raise UnknownCameraError(
                f"no camera named {key!r} in the rig; cameras are {self.names}"
            )
        return self.cameras[key]

    def __contains__(self, name: object) -> bool:
        return name in self.names

    def index(self, name: str) -> int:
        """Position of the camera called ``name``."""
        try:
            return self.names.index(name)
        except ValueError:
            raise UnknownCameraError(
                f"no camera named {name!r} in the rig; cameras are {self.names}"
            ) from None

    def subset(self, names: Iterable[str | int]) -> CameraRig:
        """A rig with only the given cameras, in the given order."""
        return CameraRig(tuple(self[n] for n in names), self.metadata)

    def with_metadata(self, **metadata: Any) -> CameraRig:
        """A copy whose metadata is updated with ``metadata``."""
        md = dict(self.metadata)
        md.update(metadata)
        return CameraRig(self.cameras, md)

    # -- stacked parameters (camera axis first) ------------------------------------
    @property
    def K(self) -> np.ndarray:
        """Intrinsic matrices, (C, 3, 3)."""
        return np.stack([c.K for c in self.cameras])

    @property
    def dist(self) -> np.ndarray:
        """Distortion coefficients, (C, 5)."""
        return np.stack([c.dist for c in self.cameras])

    @property
    def R(self) -> np.ndarray:
        """World→camera rotations, (C, 3, 3)."""
        return np.stack([c.R for c in self.cameras])

    @property
    def t(self) -> np.ndarray:
        """World→camera translations in mm, (C, 3)."""
        return np.stack([c.t for c in self.cameras])

    @property
    def centers(self) -> np.ndarray:
        """Camera centres in world mm, (C, 3)."""
        return np.stack([c.center for c in self.cameras])

    @property
    def sizes(self) -> np.ndarray:
        """Image sizes (width, height), (C, 2) int."""
        return np.array([c.size for c in self.cameras], dtype=np.int64)

    def allclose(self, other: CameraRig, rtol: float = 1e-9, atol: float = 1e-9) -> bool:
        """True when both rigs have the same cameras in the same order (see Camera.allclose)."""
        return len(self) == len(other) and all(
            a.allclose(b, rtol=rtol, atol=atol) for a, b in zip(self, other)
        )

    def project(self, points: np.ndarray, distort: bool = True) -> np.ndarray:
        """Project world points into every camera.

        Args:
            points: (..., P, 3) world points in mm (NaN allowed).
            distort: apply the lens distortion (True) or the pure pinhole model (False).

        Returns:
            (..., C, P, 2) pixel coordinates; NaN for NaN input or points behind a camera.
        """
        X = check_last(points, 3, "points")
        if X.ndim < 2:
            raise ValueError(f"points must have shape (..., P, 3), got shape {X.shape}")
        bent = distort and any(c.has_distortion for c in self.cameras)
        # all cameras at once: points (..., 1, P, 3) against the stacked parameters
        return project_points(
            X[..., None, :, :],
            self.K[:, None],
            self.R,
            self.t[:, None, :],
            self.dist[:, None, :] if bent else None,
        )

    def __repr__(self) -> str:
        return f"CameraRig({len(self)} cameras: {', '.join(self.names)})"
