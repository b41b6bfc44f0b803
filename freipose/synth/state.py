"""The kinematic state of the synthetic rodent per frame (:class:`MotionState`).

The motion model (:func:`~freipose.synth.motion.simulate_motion`) produces it and the body
builder (:func:`~freipose.synth.body.build_body`) turns it into ellipsoids and keypoints.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class MotionState:
    """Kinematic state of the animal per frame (T frames); input of ``build_body``.

    Attributes:
        root_xy: (T, 2) floor point under the torso centre, mm.
        yaw: (T,) heading (rad, 0 = +x).
        pitch: (T,) torso pitch (rad, > 0 nose up; rearing).
        bend: (T,) yaw of the chest relative to the haunch (rad).
        head_yaw, head_pitch, head_roll: (T,) head orientation relative to the chest (rad).
        rear_weight: (T,) 0..1, how far the front paws are lifted to the chest.
        feet: (T, 4, 3) planted/swinging positions of the front paw centres (right, left) and
            hind toe tips (right, left).
        foot_offsets: (T, 4, 3) stimulation offsets added to the feet.
        heel_angle: (T, 2) elevation of the hind feet (ankle above toe), rad.
        foot_yaw: (T, 2) heading of the hind feet, rad.
        tail_sway: (T, 2) sway amplitude and phase.
        tail_curl: (T,) total tail bend (rad).
        arena_half: (2,) half inner size of the arena (tail kept inside), or None.
        time: (T,) seconds.
    """

    root_xy: np.ndarray
    yaw: np.ndarray
    pitch: np.ndarray
    bend: np.ndarray
    head_yaw: np.ndarray
    head_pitch: np.ndarray
    head_roll: np.ndarray
    rear_weight: np.ndarray
    feet: np.ndarray
    foot_offsets: np.ndarray
    heel_angle: np.ndarray
    foot_yaw: np.ndarray
    tail_sway: np.ndarray
    tail_curl: np.ndarray
    arena_half: tuple[float, float] | None
    time: np.ndarray


__all__ = ["MotionState"]
