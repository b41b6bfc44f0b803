"""Validation of the request bodies of the labeling API.

A save of one instant is a JSON object::

    {"version": 3,
     "labels": {"cam0": {"Nose": {"state": "visible", "x": 101.5, "y": 88.25},
                         "Tail": {"state": "occluded"}},
                "cam1": {"Nose": {"state": "notinview"}}}}

``labels`` replaces the instant's labels: a keypoint missing there is unlabeled. A
visible label needs ``x`` and ``y`` inside the camera's image (pixel origin at the centre
of the top-left pixel: ``-0.5 <= x <= width - 0.5``); other states take no coordinates.
"""

from __future__ import annotations

import json
import math
import reprlib
from typing import Any

import numpy as np

from freipose.geometry.camera import CameraRig
from freipose.labelui.geometry import STATE_CODES, VISIBLE

MAX_BODY_BYTES = 64 * 1024


class BodyError(ValueError):
    """A request body does not follow the schema; the message says where and why."""


def _show(value: Any) -> str:
    """A short repr of a value of the body, for a message (nesting and length cut)."""
    shown = reprlib.Repr()
    shown.maxlevel, shown.maxstring, shown.maxother = 2, 40, 40
    return shown.repr(value)


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise BodyError(f"{where} must be a number, got {_show(value)}")
    try:
        v = float(value)
    except OverflowError:  # an integer beyond the float range
        v = math.inf
    if not math.isfinite(v):
        raise BodyError(f"{where} must be finite, got {_show(value)}")
    return v


def _label(entry: Any, where: str, size: tuple[int, int]) -> tuple[int, float, float]:
    """One label entry -> (state code, x, y) (NaN coordinates unless visible)."""
    if not isinstance(entry, dict):
        raise BodyError(
            f"{where} must be an object with 'state' (and 'x', 'y'), got {_show(entry)}"
        )
    unknown = sorted(set(entry) - {"state", "x", "y"})
    if unknown:
        raise BodyError(f"{where}: unknown fields {_show(unknown)}")
    state = entry.get("state")
    if not isinstance(state, str) or state not in STATE_CODES:
        raise BodyError(f"{where}.state must be one of {sorted(STATE_CODES)}, got {_show(state)}")
    code = STATE_CODES[state]
    if code != VISIBLE:
        if "x" in entry or "y" in entry:
            raise BodyError(f"{where}: a {state!r} label takes no coordinates")
        return code, math.nan, math.nan
    x = _number(entry.get("x"), f"{where}.x")
    y = _number(entry.get("y"), f"{where}.y")
    w, h = size
    if not (-0.5 <= x <= w - 0.5 and -0.5 <= y <= h - 0.5):
        raise BodyError(
            f"{where}: ({x}, {y}) is outside the {w}x{h} image (-0.5 <= x <= {w - 0.5}, "
            f"-0.5 <= y <= {h - 0.5})"
        )
    return code, x, y


def parse_save(
    body: Any, rig: CameraRig, keypoints: tuple[str, ...]
) -> tuple[int, np.ndarray, np.ndarray]:
    """Check a save body against the session's cameras and the skeleton's keypoints.

    Args:
        body: the decoded JSON body.
        rig: the session's cameras (V).
        keypoints: the skeleton's keypoints (K).

    Returns:
        ``(version, points (V, K, 2), status (V, K))``.

    Raises:
        BodyError: the body does not follow the schema (unknown camera or keypoint, a
            coordinate outside the image, a wrong type).
    """
    if not isinstance(body, dict):
        raise BodyError("the body must be a JSON object with 'version' and 'labels'")
    unknown = sorted(set(body) - {"version", "labels"})
    if unknown:
        raise BodyError(f"unknown fields {_show(unknown)}; a save has 'version' and 'labels'")
    version = body.get("version")
    if isinstance(version, bool) or not isinstance(version, int) or version < 0:
        raise BodyError(f"version must be a non-negative integer, got {_show(version)}")
    labels = body.get("labels")
    if not isinstance(labels, dict):
        raise BodyError(
            f"labels must be an object camera -> keypoint -> label, got {_show(labels)}"
        )
    V, K = len(rig), len(keypoints)
    points = np.full((V, K, 2), np.nan)
    status = np.zeros((V, K), np.int8)
    for cam, per_kp in labels.items():
        if cam not in rig.names:
            raise BodyError(f"unknown camera {_show(cam)}; this session has {rig.names}")
        if not isinstance(per_kp, dict):
            raise BodyError(f"labels[{_show(cam)}] must be an object keypoint -> label")
        v = rig.index(cam)
        for kp, entry in per_kp.items():
            if kp not in keypoints:
                raise BodyError(f"unknown keypoint {_show(kp)}; the skeleton has {list(keypoints)}")
            k = keypoints.index(kp)
            code, x, y = _label(entry, f"labels[{_show(cam)}][{_show(kp)}]", rig[cam].size)
            status[v, k] = code
            points[v, k] = (x, y)
    return version, points, status


def parse_body(
    raw: bytes, rig: CameraRig, keypoints: tuple[str, ...]
) -> tuple[int, np.ndarray, np.ndarray]:
    """Decode a save's JSON body and check it with :func:`parse_save`.

    Raises:
        BodyError: the body is not JSON (or UTF-8), nests deeper than the decoder allows,
            or does not follow the schema.
    """
    try:
        body = json.loads(raw)
    except RecursionError:
        raise BodyError(
            "the body nests too deeply; a save is an object camera -> keypoint -> label"
        ) from None
    except ValueError as exc:  # also a body that is not UTF-8
        raise BodyError(f"the body is not valid JSON ({exc})") from None
    return parse_save(body, rig, keypoints)
