"""``freipose synth``: synthetic multi-camera recordings of a moving rodent with exact ground truth.

Public API:

* :class:`SceneConfig`, :func:`generate_session` -> :class:`SessionPaths`: a session folder
  with one video per camera, ``true_calibration.toml``, ``labels.h5`` (exact 3D keypoints, their
  projections and per-view visibility for every frame), ``events.csv`` and ``scene.toml``;
* :func:`default_rig`, :func:`load_rig_file`, :class:`ArenaConfig`: camera rigs and the arena;
* :mod:`freipose.synth.motion`: :func:`simulate_motion` -> :class:`MotionState`,
  :func:`simulate_trajectory` (T, 12, 3) keypoint trajectories; :class:`StimulationConfig`
  (:mod:`freipose.synth.stimulation`);
* :mod:`freipose.synth.board`: :func:`board_poses`, :func:`render_board_frames`,
  :func:`write_board_videos` (calibration videos);
* :class:`RatBody`, :func:`build_body`: the articulated ellipsoid animal (rat or mouse);
* :mod:`freipose.synth.conditions`: the conditions of real rigs (grayscale, fisheye lenses,
  reflective walls, resting, bedding, a mouse, label files of other tools) and domain
  randomisation (``SceneConfig(seed=S, randomize=True)``), all plain ``SceneConfig`` keys;
* several animals (``SceneConfig(animals=2..4)``): :mod:`freipose.synth.social`
  (:func:`simulate_social` -> :class:`SocialMotion`: meeting, crossing, climbing over;
  ``combine_geometries``) and :mod:`freipose.synth.social_scene` (``true_poses.h5``, the
  labels with ``individual``, :func:`animal_views`: per-animal visibility and occlusion by
  the other animals).
"""

from freipose.synth.board import board_poses, default_board, render_board_frames, write_board_videos
from freipose.synth.body import RAT_KEYPOINTS, BodyGeometry, RatBody, build_body
from freipose.synth.errors import RigFileError, SynthError
from freipose.synth.motion import simulate_motion, simulate_trajectory
from freipose.synth.rig import ArenaConfig, default_rig, load_rig_file, rig_from_dict
from freipose.synth.scene import SceneConfig, SessionPaths, build_scene, generate_session
from freipose.synth.social import SocialMotion, simulate_social
from freipose.synth.social_scene import TRUE_POSES_NAME, animal_views
from freipose.synth.state import MotionState
from freipose.synth.stimulation import StimulationConfig
from freipose.synth.visibility import keypoint_visibility

__all__ = [
    "RAT_KEYPOINTS",
    "TRUE_POSES_NAME",
    "ArenaConfig",
    "BodyGeometry",
    "MotionState",
    "RatBody",
    "RigFileError",
    "SceneConfig",
    "SessionPaths",
    "SocialMotion",
    "StimulationConfig",
    "animal_views",
    "SynthError",
    "board_poses",
    "build_body",
    "build_scene",
    "default_board",
    "default_rig",
    "generate_session",
    "keypoint_visibility",
    "load_rig_file",
    "render_board_frames",
    "rig_from_dict",
    "simulate_motion",
    "simulate_social",
    "simulate_trajectory",
    "write_board_videos",
]
