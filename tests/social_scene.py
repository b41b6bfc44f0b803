"""Simulated social scenes for the multi-animal tests: known 3D tracks seen as boxes.

:func:`social_scene` moves 2-3 animals on known trajectories (crossing paths, a stretch of
side-by-side contact, a bounded random walk) and :func:`observe` turns them into what a
detector gives per view: one box per animal around its projected body, with views
dropped (occlusion), touching animals merged into one box, false boxes, and per-box
appearance vectors (the animal's coat colour plus noise).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from freipose.geometry import CameraRig, project_rig

KEYPOINTS = ("nose", "ear_l", "ear_r", "back", "tail")


@dataclass(frozen=True, eq=False)
class Scene:
    """Known truth: centres (T, A, 3), keypoints (T, A, 5, 3), headings (T, A), colours (A, 3)."""

    centres: np.ndarray
    keypoints: np.ndarray
    heading: np.ndarray
    colours: np.ndarray
    fps: float


def _body(centre: np.ndarray, heading: np.ndarray, length: float) -> np.ndarray:
    """Keypoints (T, 5, 3) of a rat-sized body centred at ``centre`` (T, 3), facing ``heading``."""
    fwd = np.stack([np.cos(heading), np.sin(heading), np.zeros_like(heading)], -1)
    left = np.stack([-np.sin(heading), np.cos(heading), np.zeros_like(heading)], -1)
    up = np.array([0.0, 0.0, 1.0])
    h = length / 2
    offs = [(h, 0, 10), (0.6 * h, 12, 25), (0.6 * h, -12, 25), (0, 0, 30), (-h, 0, 0)]
    return np.stack([centre + a * fwd + b * left + c * up for a, b, c in offs], axis=1)  # (T, 5, 3)


# (knots in [0, 1] of the session, xy mm): 0 and 1 meet, walk side by side in contact (75 mm
# apart, about a body width) and cross each other's path as they part; 2 crosses 0's path.
WAYPOINTS = (
    ([0.0, 0.35, 0.6, 0.65, 1.0], [(-220, 150), (-40, 38), (60, 38), (62, 38), (220, -180)]),
    ([0.0, 0.35, 0.6, 0.75, 1.0], [(220, -150), (-40, -37), (60, -37), (200, -37), (200, 200)]),
    ([0.0, 0.5, 1.0], [(-180, -220), (-150, 0), (-60, 230)]),
)


def social_scene(
    n_animals: int = 2, n_frames: int = 300, fps: float = 30.0, seed: int = 0
) -> Scene:
    """Animals that meet, touch side by side, cross paths and wander (see ``WAYPOINTS``)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_frames) / fps
    u = t / max(t[-1], 1e-9)
    centres = np.zeros((n_frames, n_animals, 3))
    for a in range(n_animals):
        knots, xy = (
            WAYPOINTS[a] if a < len(WAYPOINTS) else ([0.0, 1.0], rng.uniform(-200, 200, (2, 2)))
        )
        for d in range(2):
            centres[:, a, d] = np.interp(u, knots, np.asarray(xy)[:, d])
        centres[:, a, :2] += 6 * np.sin(2 * np.pi * (0.4 + 0.1 * a) * t[:, None] + [a, 2 * a])
    centres[..., 2] = 40.0
    vel = np.gradient(centres, axis=0)
    heading = np.arctan2(vel[..., 1], vel[..., 0])
    kp = np.stack([_body(centres[:, a], heading[:, a], 200.0) for a in range(n_animals)], 1)
    colours = np.array([[0.9, 0.9, 0.85], [0.3, 0.25, 0.2], [0.75, 0.5, 0.3], [0.5, 0.5, 0.6]])
    return Scene(centres, kp, heading, colours[:n_animals], fps)


@dataclass(frozen=True, eq=False)
class Observation:
    """Per frame and view: boxes (n, 4), their true animal (n,) (-1 false), appearance (n, 3)."""

    boxes: list[list[np.ndarray]]
    truth: list[list[np.ndarray]]
    appearance: list[list[np.ndarray]]
    visible: np.ndarray  # (T, C, A) the animal has a box of its own in the view


def true_boxes(scene: Scene, rig: CameraRig, margin: float = 0.1) -> np.ndarray:
    """(T, C, A, 4) boxes around the projected body (keypoints plus a body-width disc)."""
    kp = scene.keypoints  # (T, A, 5, 3)
    ring = np.stack(
        [np.cos(np.linspace(0, 2 * np.pi, 8, endpoint=False)) * 45,
         np.sin(np.linspace(0, 2 * np.pi, 8, endpoint=False)) * 45, np.zeros(8)], -1
    )  # fmt: skip
    pts = np.concatenate([kp, scene.centres[:, :, None] + ring], axis=2)  # (T, A, P, 3)
    uv = project_rig(pts, rig)  # (T, A, C, P, 2)
    uv = np.moveaxis(uv, 2, 1)  # (T, C, A, P, 2)
    lo, hi = uv.min(-2), uv.max(-2)
    pad = margin * (hi - lo).max(-1, keepdims=True)
    return np.concatenate([lo - pad, hi + pad], -1)


def observe(
    scene: Scene,
    rig: CameraRig,
    seed: int = 0,
    p_drop: float = 0.1,
    p_false: float = 0.1,
    hidden: dict[tuple[int, int], tuple[int, int]] | None = None,
    merge_iou: float = 0.5,
    jitter_px: float = 2.0,
) -> Observation:
    """What a detector sees: boxes per frame and view (see the module docstring).

    Args:
        scene: the truth.
        rig: the cameras.
        seed: noise seed.
        p_drop: probability that an animal's box is missing in a view (occlusion, miss).
        p_false: probability of one false box per frame and view.
        hidden: ``{(animal, camera): (first, last)}`` frames where the animal is fully
            hidden in that camera.
        merge_iou: boxes of two animals overlapping more than this become one box (the
            union) given to the larger-area animal; the other has no box of its own.
        jitter_px: noise of box edges.
    """
    rng = np.random.default_rng(seed)
    tb = true_boxes(scene, rig)
    t_n, c_n, a_n, _ = tb.shape
    boxes, truth, app = [], [], []
    visible = np.ones((t_n, c_n, a_n), bool)
    for t in range(t_n):
        fb, ft, fa = [], [], []
        for c in range(c_n):
            b = tb[t, c] + rng.normal(0, jitter_px, (a_n, 4))
            keep = rng.random(a_n) >= p_drop
            for (a, cam), (f0, f1) in (hidden or {}).items():
                if cam == c and f0 <= t <= f1:
                    keep[a] = False
            w = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
            for i in range(a_n):
                for j in range(i + 1, a_n):
                    if keep[i] and keep[j] and _iou(b[i], b[j]) > merge_iou:
                        big, small = (i, j) if w[i] >= w[j] else (j, i)
                        b[big] = np.r_[
                            np.minimum(b[i, :2], b[j, :2]), np.maximum(b[i, 2:], b[j, 2:])
                        ]
                        keep[small] = False
            visible[t, c] = keep
            lab = list(np.flatnonzero(keep))
            bb = [b[a] for a in lab]
            aa = [scene.colours[a] + rng.normal(0, 0.03, 3) for a in lab]
            if rng.random() < p_false:
                wsz, hsz = rig[c].size
                s = rng.uniform(15, 40)
                x, y = rng.uniform(s, wsz - s), rng.uniform(s, hsz - s)
                bb.append(np.array([x - s, y - s, x + s, y + s]))
                lab.append(-1)
                aa.append(rng.uniform(0, 1, 3))
            fb.append(np.asarray(bb).reshape(-1, 4))
            ft.append(np.asarray(lab, dtype=np.int64))
            fa.append(np.asarray(aa).reshape(-1, 3))
        boxes.append(fb)
        truth.append(ft)
        app.append(fa)
    return Observation(boxes, truth, app, visible)


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    x0, y0 = max(a[0], b[0]), max(a[1], b[1])
    x1, y1 = min(a[2], b[2]), min(a[3], b[3])
    inter = max(0.0, x1 - x0) * max(0.0, y1 - y0)
    ua = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / ua if ua > 0 else 0.0
