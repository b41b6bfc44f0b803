"""Constant-pose sanity references: what a network must beat to have learned anything.

A network that has learned poses must beat answers that look at no image. Two such
answers are built from the training labels' median pose in a body-centred frame (each
training instant's keypoints minus that instant's centre, the mean of its labeled 3D
points; the per-keypoint median over the instants):

* ``median pose at held-out centre``: that pose placed at each held-out instant's centre
  (the centre the networks' cube is placed on, so it is the reference for a network
  evaluated with the cube on the label centre);
* ``median pose at training centre``: that pose placed at the mean centre of the training
  instants (an answer that does not even look at where the animal is).

On an animal that mostly rests, the first can be hard to beat.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from freipose.geometry.crops import label_centers

AT_HELD_OUT = "median pose at held-out centre"
AT_TRAINING = "median pose at training centre"


def median_pose(train3d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The training labels' median body-centred pose and their mean centre.

    Args:
        train3d: (N, K, 3) training 3D labels (mm), NaN where unlabeled.

    Returns:
        ``(pose, centre)``: (K, 3) per-keypoint median of the centred poses (NaN for a
        keypoint never labeled) and the (3,) mean of the instants' centres.

    Raises:
        ValueError: no training instant has a labeled 3D point.
    """
    p = np.asarray(train3d, np.float64)
    c = label_centers(p)
    ok = np.isfinite(c).all(-1)
    if not ok.any():
        raise ValueError("the training labels have no instant with a labeled 3D point")
    centred = p[ok] - c[ok, None, :]
    labeled = np.isfinite(centred).all(-1).any(0)
    pose = np.full(p.shape[1:], np.nan)
    pose[labeled] = np.nanmedian(centred[:, labeled], axis=0)
    return pose, c[ok].mean(0)


def reference_predictions(train3d: np.ndarray, gt: np.ndarray) -> dict[str, np.ndarray]:
    """The two constant-pose answers for every held-out instant.

    Args:
        train3d: (N, K, 3) training 3D labels (mm), NaN where unlabeled.
        gt: (M, K, 3) held-out 3D labels (mm), NaN where unknown.

    Returns:
        :data:`AT_HELD_OUT` and :data:`AT_TRAINING` -> (M, K, 3) predictions.

    Raises:
        ValueError: the keypoint counts differ, or the training labels have no 3D point.
    """
    gt = np.asarray(gt, np.float64)
    if np.shape(train3d)[1:] != gt.shape[1:]:
        raise ValueError(
            f"training labels {np.shape(train3d)} and held-out labels {gt.shape} must have the "
            "same keypoints"
        )
    pose, centre = median_pose(train3d)
    held = label_centers(gt)
    return {
        AT_HELD_OUT: pose[None] + held[:, None, :],
        AT_TRAINING: np.broadcast_to(pose + centre, gt.shape).copy(),
    }


def reference_summary(errors: Mapping[str, np.ndarray]) -> dict[str, dict[str, Any]]:
    """``references`` of metrics.json: the median JPE of each reference.

    Args:
        errors: reference name -> (M, K) JPE (mm), NaN where unlabeled.

    Returns:
        name -> ``{"median_mm": float, "n": int}``.
    """
    out = {}
    for name, e in errors.items():
        v = e[~np.isnan(e)]
        out[name] = {
            "median_mm": float(np.median(np.minimum(v, 1e12))) if v.size else float("nan"),
            "n": int(v.size),
        }
    return out


def beats_reference_warnings(
    medians: Mapping[str, float], references: Mapping[str, Mapping[str, Any]]
) -> list[str]:
    """A warning for each network whose median JPE is not below the held-out-centre reference.

    Args:
        medians: network result name -> median JPE (mm).
        references: :func:`reference_summary`'s result.

    Returns:
        One ``WARNING: ...`` line per network that does not beat :data:`AT_HELD_OUT`.
    """
    ref = references.get(AT_HELD_OUT, {}).get("median_mm", float("nan"))
    if not np.isfinite(ref):
        return []
    return [
        f"WARNING: {name} (median JPE {m:.2f} mm) does not beat the constant-pose reference "
        f"({AT_HELD_OUT}: {ref:.2f} mm): it has not learned more than the training labels' "
        "median pose; train longer or on more labels, add unlabeled video ([unlabeled]), and "
        "give validation labels ([data] validation_labels) so that training chooses the 2D "
        "decoding window (the whole maps help a network whose map peaks are still off)"
        for name, m in medians.items()
        if not m < ref
    ]
