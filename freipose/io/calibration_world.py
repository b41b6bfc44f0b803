"""The world's up direction and floor height stored with a calibration.

A calibration's ``[metadata]`` table may hold ``up`` (the world's unit up vector),
``up_source`` (how it was obtained: the board on the floor, the user, the labeled animal)
and ``floor_mm`` (the floor is the plane ``up · X = floor_mm``). Files without them (older
files, other tools' formats, a calibration whose world is a camera's frame) have no known
up: :func:`resolve_up` then estimates it from the animal's 3D points when it is given
some, else assumes world z and says so in a warning.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from freipose.errors import FreiPoseError
from freipose.geometry.camera import CameraRig
from freipose.geometry.floor import estimate_up

log = logging.getLogger(__name__)

__all__ = [
    "UP_KEYS",
    "WorldUp",
    "resolve_up",
    "rig_with_up",
    "stored_up_or_z",
    "up_from_labels",
    "with_world_up",
    "world_up",
]

UP_KEYS = ("up", "up_source", "floor_mm")
# The largest scatter ratio (smallest / middle eigenvalue) at which the labels fix the up.
MAX_FLATNESS = 0.5
# The largest uncertainty (95th percentile over resampled instants, degrees) of an
# estimated up that is stored or used.
MAX_UP_UNCERTAINTY_DEG = 3.0


class WorldUpError(FreiPoseError):
    """An up direction cannot be set or estimated (the message says what to pass)."""


@dataclass(frozen=True, eq=False)
class WorldUp:
    """The world's up direction.

    Attributes:
        up: (3,) unit up vector in the world frame.
        source: how it was obtained (for files and messages).
        floor: the floor's height along ``up`` (mm; ``up · X = floor``), None if unknown.
    """

    up: np.ndarray
    source: str
    floor: float | None = None

    def __post_init__(self) -> None:
        """Check the vector and scale it to unit length."""
        u = np.asarray(self.up, dtype=np.float64).reshape(-1)
        if u.shape != (3,) or not np.isfinite(u).all() or np.linalg.norm(u) < 1e-9:
            raise WorldUpError(
                f"the up direction must be 3 finite numbers, not all zero (e.g. --up 0,0,1); "
                f"got {self.up!r}"
            )
        object.__setattr__(self, "up", u / np.linalg.norm(u))

    def metadata(self) -> dict[str, Any]:
        """The calibration-metadata entries for this up direction."""
        md: dict[str, Any] = {"up": [round(float(x), 9) for x in self.up], "up_source": self.source}
        if self.floor is not None:
            md["floor_mm"] = round(float(self.floor), 4)
        return md


def world_up(rig: CameraRig | Mapping[str, Any]) -> WorldUp | None:
    """The up direction a rig's metadata (or a metadata mapping) stores, or None."""
    md = rig.metadata if isinstance(rig, CameraRig) else rig
    if "up" not in md:
        return None
    floor = md.get("floor_mm")
    try:
        return WorldUp(
            np.asarray(md["up"], dtype=np.float64),
            str(md.get("up_source", "calibration file")),
            None if floor is None else float(floor),
        )
    except (TypeError, ValueError) as exc:
        raise WorldUpError(
            f"the calibration's metadata.up must be 3 numbers, got {md['up']!r}"
        ) from exc


def with_world_up(rig: CameraRig, up: WorldUp | None) -> CameraRig:
    """The rig with ``up`` in its metadata (None: without any up direction)."""
    md = {k: v for k, v in rig.metadata.items() if k not in UP_KEYS}
    if up is not None:
        md.update(up.metadata())
    return CameraRig(rig.cameras, md)


def stored_up_or_z(rig: CameraRig) -> np.ndarray:
    """(3,) the rig's stored unit up, else world z, without a warning.

    For callers that need a direction before one can be estimated, or that warn about the
    assumption elsewhere (training warns per session when it resolves the up).
    """
    known = world_up(rig)
    return np.array([0.0, 0.0, 1.0]) if known is None else known.up


def up_from_labels(rig: CameraRig, points: np.ndarray, what: str = "labeled") -> WorldUp:
    """Estimate the up direction from the labeled (or predicted) animal's 3D points.

    Args:
        rig: the cameras (their centres decide which side of the floor is up).
        points: (..., 3) labeled 3D points over time (world mm).
        what: what the points are (``"labeled"``, ``"predicted"``; for the messages).

    Returns:
        The estimate, its floor height and a source naming the evidence.

    Raises:
        WorldUpError: too few points, points that do not fix a plane (an animal that
            never moved over the floor), or an up that the points determine only to more
            than ``MAX_UP_UNCERTAINTY_DEG`` (too few instants, or all along one line).
    """
    est = estimate_up(points, rig.centers)
    if est is None:
        raise WorldUpError(
            f"cannot estimate the up direction: fewer than 10 {what} 3D points; give it with "
            "freipose calib up CALIBRATION --up X,Y,Z"
        )
    if est.flatness > MAX_FLATNESS:
        raise WorldUpError(
            f"cannot estimate the up direction from the {what} points: they do not spread "
            f"over a plane (scatter ratio {est.flatness:.2f}, need at most {MAX_FLATNESS}; the "
            f"animal hardly moved); give it with freipose calib up CALIBRATION --up X,Y,Z, or "
            f"calibrate with --origin-frame N (a frame with the board on the floor)"
        )
    if not est.uncertainty_deg <= MAX_UP_UNCERTAINTY_DEG:
        more = (
            "label more instants spread over the whole arena (typically 100 or more)"
            if what == "labeled"
            else f"use more {what} frames of the animal moving over the whole arena"
        )
        raise WorldUpError(
            f"cannot estimate the up direction from the {what} points: {est.instants} "
            f"instants determine it only to within {est.uncertainty_deg:.1f} degrees "
            f"(95 % over resampled instants; need at most {MAX_UP_UNCERTAINTY_DEG:g}); "
            f"{more}, or give it with freipose calib up CALIBRATION --up X,Y,Z"
        )
    return WorldUp(
        est.up,
        f"estimated from {est.points} {what} 3D points of {est.instants} instants (the "
        f"plane the animal moves on, within {est.uncertainty_deg:.1f} degrees; "
        f"{est.cameras_above} of {len(rig)} cameras above it)",
        est.floor,
    )


def resolve_up(
    rig: CameraRig | None,
    points: np.ndarray | None = None,
    purpose: str = "the up direction",
    what: str = "labeled",
) -> WorldUp:
    """The rig's stored up, else one estimated from ``points``, else world z (warned).

    Args:
        rig: the calibration (None: no calibration).
        points: (..., 3) 3D points of the animal over time (world mm), or None.
        purpose: what the up is used for (for the warning).
        what: what the points are (``"labeled"``, ``"predicted"``; for the messages).

    Returns:
        The up direction; its ``source`` says which of the three it is.
    """
    stored = world_up(rig) if rig is not None else None
    if stored is not None:
        return stored
    reason = "the calibration stores no up direction"
    if rig is not None and points is not None:
        try:
            est = up_from_labels(rig, points, what)
        except WorldUpError as exc:
            reason = f"{reason}, and the {what} points give none ({exc})"
        else:
            log.warning(
                "%s; for %s it is %s: up = %s (set it with freipose calib up)",
                reason,
                purpose,
                est.source,
                np.round(est.up, 3).tolist(),
            )
            return est
    log.warning(
        "%s; %s assumes world z is up (set it with freipose calib up CALIBRATION --up X,Y,Z, "
        "or calibrate with --origin-frame N)",
        reason,
        purpose,
    )
    return WorldUp(np.array([0.0, 0.0, 1.0]), "assumed (world z)")


def rig_with_up(
    rig: CameraRig, points: np.ndarray | None = None, purpose: str = "the up direction"
) -> CameraRig:
    """``rig`` with the up of :func:`resolve_up` in its metadata (unchanged if stored).

    An assumed world z is not stored: the rig then has no up, as before.

    Args:
        rig: the calibration.
        points: (..., 3) 3D points of the animal over time (world mm), or None.
        purpose: what the up is used for (for the warning).

    Returns:
        The rig, with an estimated up when it had none and ``points`` give one.
    """
    if world_up(rig) is not None:
        return rig
    found = resolve_up(rig, points, purpose)
    return rig if found.source.startswith("assumed") else with_world_up(rig, found)
