"""How predicted poses fail beyond their joint position error: collapsed or swapped pairs.

A network can reach a moderate JPE while it places the left and right keypoints of a pair
(ears, eyes, paws) on the body's midline: each keypoint is then half a pair's distance
from the truth, yet the pose is no longer the animal's. :func:`failure_modes` measures,
per symmetric left/right pair of the skeleton, the median distance between the two
keypoints in the predictions and in the truth, the share of instants whose prediction
is closer to the truth with left and right swapped, and per bone (limb) the median
predicted and true length, and it writes a warning for each collapsed or often swapped
pair. A pair or bone without any instant to measure it on has no values (None) and says
why in ``missing``: ``not labeled`` (the truth never has both ends) or ``not predicted``
(the predictions never have both where the truth does).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from freipose.skeleton import PointRef, Skeleton, left_right_pairs

COLLAPSE_RATIO = 0.5  # a pair predicted closer than this share of its true distance
SWAP_WARN_RATE = 0.25  # a pair swapped in at least this share of instants
NOT_LABELED = "not labeled"
NOT_PREDICTED = "not predicted"


def _median(values: np.ndarray) -> float | None:
    """Median of the finite values (None when there is none)."""
    v = values[np.isfinite(values)]
    return float(np.median(v)) if v.size else None


def _missing(labeled: np.ndarray, ok: np.ndarray) -> str | None:
    """Why nothing was measured (None: something was).

    Args:
        labeled: (N,) the truth has the values.
        ok: (N,) the truth and the prediction have them.
    """
    if ok.any():
        return None
    return NOT_PREDICTED if labeled.any() else NOT_LABELED


def _pair(pred: np.ndarray, gt: np.ndarray, left: int, right: int) -> dict[str, Any]:
    """Distances and swap rate of one (left, right) pair over the instants with both known."""
    labeled = np.isfinite(gt[:, [left, right]]).all((1, 2))
    ok = np.isfinite(pred[:, [left, right]]).all((1, 2)) & labeled
    pl, pr, gl, gr = pred[ok, left], pred[ok, right], gt[ok, left], gt[ok, right]
    kept = np.linalg.norm(pl - gl, axis=-1) + np.linalg.norm(pr - gr, axis=-1)
    swapped = np.linalg.norm(pl - gr, axis=-1) + np.linalg.norm(pr - gl, axis=-1)
    return {
        "predicted_mm": _median(np.linalg.norm(pl - pr, axis=-1)),
        "true_mm": _median(np.linalg.norm(gl - gr, axis=-1)),
        "swap_rate": float((swapped < kept).mean()) if ok.any() else None,
        "instants": int(ok.sum()),
        "missing": _missing(labeled, ok),
    }


def _mm(value: float | None) -> str:
    """A length for the terminal (``-`` for None)."""
    return "-" if value is None else f"{value:.1f}"


def _ref_name(skeleton: Skeleton, ref: PointRef) -> str:
    """A limb end's name: the keypoint, or ``mean(A, B)`` for the midpoint of several."""
    names = [skeleton.keypoints[i] for i in ref]
    return names[0] if len(names) == 1 else f"mean({', '.join(names)})"


def failure_modes(
    pred: np.ndarray,
    gt: np.ndarray,
    skeleton: Skeleton,
    method: str = "",
    collapse_ratio: float = COLLAPSE_RATIO,
) -> dict[str, Any]:
    """Symmetric-pair distances, left/right swap rates and bone lengths against the truth.

    A pair is *collapsed* when its median predicted distance is below ``collapse_ratio``
    times its median true distance; it is *swapped* at an instant where exchanging the
    predicted left and right keypoints brings both closer to the truth (sum of the two
    distances).

    Args:
        pred: (N, K, 3) predicted keypoints (mm), NaN where missing.
        gt: (N, K, 3) true keypoints (mm), NaN where unknown.
        skeleton: the K keypoints' skeleton (its left/right pairs and limbs).
        method: the name the warnings start with (e.g. ``voxel_P1``).
        collapse_ratio: see above.

    Returns:
        ``pairs``: per pair ``left``, ``right``, ``predicted_mm``, ``true_mm``,
        ``swap_rate``, ``instants``, ``collapsed`` and ``missing``; ``bones``: per limb
        ``bone``, ``predicted_mm`` and ``true_mm`` (medians) and ``missing``; ``warnings``:
        one line per collapsed or often swapped pair that is not collapsed. Values that
        nothing measured are None, ``missing`` says why (None where measured).

    Raises:
        ValueError: ``pred`` and ``gt`` differ in shape or do not have K keypoints.
    """
    pred = np.asarray(pred, np.float64)
    gt = np.asarray(gt, np.float64)
    if pred.shape != gt.shape or pred.ndim != 3 or pred.shape[1] != skeleton.num_keypoints:
        raise ValueError(
            f"pred {pred.shape} and gt {gt.shape} must both be (N, {skeleton.num_keypoints}, 3)"
        )
    kps = skeleton.keypoints
    who = f"{method}: " if method else ""
    pairs, warnings = [], []
    for left, right in left_right_pairs(skeleton):
        p = _pair(pred, gt, left, right)
        p["collapsed"] = p["missing"] is None and p["predicted_mm"] < collapse_ratio * p["true_mm"]
        pairs.append({"left": kps[left], "right": kps[right], **p})
        if p["collapsed"]:
            warnings.append(
                f"WARNING: {who}{kps[left]} and {kps[right]} collapse onto each other: "
                f"predicted {p['predicted_mm']:.1f} mm apart, truly {p['true_mm']:.1f} mm "
                f"(medians over {p['instants']} instants)"
            )
        elif p["missing"] is None and p["swap_rate"] >= SWAP_WARN_RATE:  # (not collapsed)
            warnings.append(
                f"WARNING: {who}{kps[left]} and {kps[right]} are swapped (left for right) in "
                f"{100 * p['swap_rate']:.0f} % of {p['instants']} instants"
            )
    bones = []
    if skeleton.limbs:
        lp, lt = skeleton.limb_lengths(pred), skeleton.limb_lengths(gt)
        for j, (a, b) in enumerate(skeleton.limbs):
            ok = np.isfinite(lp[:, j]) & np.isfinite(lt[:, j])
            bones.append(
                {
                    "bone": f"{_ref_name(skeleton, a)} - {_ref_name(skeleton, b)}",
                    "predicted_mm": _median(lp[ok, j]),
                    "true_mm": _median(lt[ok, j]),
                    "missing": _missing(np.isfinite(lt[:, j]), ok),
                }
            )
    return {"pairs": pairs, "bones": bones, "warnings": warnings}


def format_failure_modes(modes: dict[str, Any]) -> list[str]:
    """Terminal lines for :func:`failure_modes`' result: a table of pairs, bones, warnings.

    Args:
        modes: what :func:`failure_modes` returned.

    Returns:
        The lines (no trailing newlines); empty when there are neither pairs nor bones.
    """
    lines = []
    if modes["pairs"]:
        lines.append("  left/right pair: distance predicted vs true (median), swap rate")
        for p in modes["pairs"]:
            name = f"    {p['left']} / {p['right']}: "
            if p.get("missing"):
                lines.append(name + p["missing"])
                continue
            swap = (
                "COLLAPSED (its swaps are chance)"
                if p["collapsed"]
                else f"swapped {100 * p['swap_rate']:.0f} %"
            )
            lines.append(f"{name}{_mm(p['predicted_mm'])} vs {_mm(p['true_mm'])} mm, {swap}")
    if modes["bones"]:
        lines.append("  bone length predicted vs true (median)")
        for b in modes["bones"]:
            what = b.get("missing") or f"{_mm(b['predicted_mm'])} vs {_mm(b['true_mm'])} mm"
            lines.append(f"    {b['bone']}: {what}")
    return lines + list(modes["warnings"])
