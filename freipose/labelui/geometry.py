"""The live geometry of one labeled instant: triangulation, projections, residuals, bones.

Labels of one time instant are an array ``points`` (V, K, 2) over the session's V cameras
and the skeleton's K keypoints, with a per-label state ``status`` (V, K) (see
:data:`UNLABELED` ... :data:`NOT_IN_VIEW`). Only *visible* labels (state
:data:`VISIBLE`) enter the triangulation.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from freipose.geometry.camera import CameraRig
from freipose.geometry.triangulation import reprojection_errors, triangulate_weighted
from freipose.skeleton import Skeleton

UNLABELED = 0
VISIBLE = 1
OCCLUDED = 2
NOT_IN_VIEW = 3
STATE_NAMES = {VISIBLE: "visible", OCCLUDED: "occluded", NOT_IN_VIEW: "notinview"}
STATE_CODES = {name: code for code, name in STATE_NAMES.items()}


@dataclass(frozen=True, eq=False)
class InstantGeometry:
    """What the labels of one instant imply.

    Attributes:
        points3d: (K, 3) world mm triangulated from the visible labels; NaN where fewer
            than two views have one.
        projected: (V, K, 2) pixels of ``points3d`` in every camera (with distortion).
        residuals: (V, K) pixel distance between each visible label and the projection
            of its keypoint's 3D point; NaN where there is no visible label or no 3D point.
    """

    points3d: np.ndarray
    projected: np.ndarray
    residuals: np.ndarray


def instant_geometry(
    points: np.ndarray,
    status: np.ndarray,
    rig: CameraRig,
    previous: InstantGeometry | None = None,
    changed: np.ndarray | None = None,
) -> InstantGeometry:
    """Triangulate the visible labels of one instant and project them into every view.

    Args:
        points: (V, K, 2) label pixels (NaN where unlabeled), V = ``len(rig)``.
        status: (V, K) label states.
        rig: the session's cameras, in the order of the V axis.
        previous: the geometry before an edit; its keypoints outside ``changed`` are kept.
        changed: (K,) bool, the keypoints whose labels the edit changed (with ``previous``).

    Returns:
        The instant's :class:`InstantGeometry` (linear DLT triangulation on undistorted
        coordinates, fast enough for every edit).
    """
    V, K = status.shape
    vis = (status == VISIBLE) & np.isfinite(points).all(-1)
    redo = np.ones(K, bool)
    if previous is not None and changed is not None:
        X = previous.points3d.copy()
        projected = previous.projected.copy()
        residuals = previous.residuals.copy()
        redo = np.asarray(changed, bool)
        X[redo], projected[:, redo], residuals[:, redo] = np.nan, np.nan, np.nan
    else:
        X = np.full((K, 3), np.nan)
        projected = np.full((V, K, 2), np.nan)
        residuals = np.full((V, K), np.nan)
    seen = np.flatnonzero(redo & (vis.sum(0) >= 2))  # only these can be triangulated
    if len(seen):
        obs = np.where(vis[..., None], points, np.nan)[:, seen].transpose(1, 0, 2)  # (S, V, 2)
        X[seen] = triangulate_weighted(obs, vis[:, seen].T.astype(np.float64), rig)
        projected[:, seen] = rig.project(X[seen], distort=True)
        residuals[:, seen] = reprojection_errors(X[seen], obs, rig).T
    return InstantGeometry(X, projected, residuals)


def bone_lengths(skeleton: Skeleton, points3d: np.ndarray) -> np.ndarray:
    """Limb lengths (mm) of 3D points (..., K, 3) -> (..., L); NaN where an end is unknown."""
    if not skeleton.limbs:
        return np.zeros(points3d.shape[:-2] + (0,))
    return skeleton.limb_lengths(np.asarray(points3d, dtype=np.float64))


def bone_report(
    skeleton: Skeleton, lengths: np.ndarray, reference: np.ndarray, tolerance: float
) -> list[dict[str, object]]:
    """Per limb: its length, the reference (median) length and whether it is far off.

    Args:
        skeleton: the skeleton (L limbs).
        lengths: (L,) this instant's limb lengths, NaN where unknown.
        reference: (L,) the labeled set's median lengths, NaN where too few are known.
        tolerance: a limb is flagged when ``|length - reference| > tolerance * reference``.

    Returns:
        One JSON-ready dict per limb with a known length: ``limb`` (index), ``length``,
        ``median`` (None if unknown) and ``flag``.
    """
    out: list[dict[str, object]] = []
    for i, (length, ref) in enumerate(zip(lengths, reference)):
        if not np.isfinite(length):
            continue
        known = bool(np.isfinite(ref) and ref > 0)
        flag = known and abs(float(length) - float(ref)) > tolerance * float(ref)
        out.append(
            {
                "limb": i,
                "length": round(float(length), 2),
                "median": round(float(ref), 2) if known else None,
                "flag": bool(flag),
            }
        )
    return out


def median_lengths(lengths: np.ndarray, min_count: int = 3) -> np.ndarray:
    """The median of (N, L) limb lengths over the instants; NaN with fewer than ``min_count``."""
    if lengths.size == 0:
        return np.full(lengths.shape[-1:], np.nan)
    count = np.isfinite(lengths).sum(0)
    with warnings.catch_warnings():  # all-NaN columns: NaN, no warning
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(lengths, axis=0)
    return np.where(count >= min_count, med, np.nan)
