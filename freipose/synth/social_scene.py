"""The files of a synthetic scene of several animals: its animals, truth and labels.

:func:`social_bodies` draws the animals (each its own individual; their coats the same,
different or each at random), :func:`animal_views` projects every animal's keypoints and
tells which are hidden, and by another animal's body, and :func:`write_social_labels`
writes ``labels.h5`` (a row per frame and animal, with ``individual``) and the truth
``true_poses.h5``: a poses file with an animal axis (``freipose.io.poses``), confidence and
identity confidence 1, and the extras ``points2d`` (T, A, C, K, 2) exact projections,
``visible2d`` (T, A, C, K), ``hidden_by_animal`` (T, A, C, K) (hidden by another animal's
body), ``on_top_of`` (T, A) (the animal it climbs over, -1: none), ``lift`` (T, A) mm and
``contact`` (T, A, A) (floor prints touching).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from freipose.geometry import CameraRig
from freipose.synth.body import APPEARANCES, MOUSE_COATS, RAT_KEYPOINTS, BodyGeometry, RatBody
from freipose.synth.rig import ArenaConfig
from freipose.synth.social import SocialMotion

TRUE_POSES_NAME = "true_poses.h5"


def animal_names(n: int) -> tuple[str, ...]:
    """(A,) the names of a scene's animals: ``animal0``, ``animal1``, ..."""
    return tuple(f"animal{a}" for a in range(n))


def social_bodies(
    animal: str,
    appearance: str,
    coat_mix: str,
    scales: Sequence[float],
    seeds: Sequence[int],
) -> tuple[RatBody, ...]:
    """The animals of a social scene, each its own individual.

    Args:
        animal: ``rat`` or ``mouse`` (the coats drawn at random).
        appearance: every animal's coat, or ``random``.
        coat_mix: with a random appearance: ``random`` (each drawn), ``same`` (the first
            one's) or ``different`` (each another coat while there are coats left).
        scales: (A,) nominal size factors.
        seeds: (A,) the individuals' seeds.

    Returns:
        (A,) the bodies.
    """
    coats = MOUSE_COATS if animal == "mouse" else APPEARANCES
    if animal == "rat" and coat_mix == "different":
        coats = (*APPEARANCES, "dark")
    bodies: list[RatBody] = []
    for size, seed in zip(scales, seeds):
        rng = np.random.default_rng(seed)
        coat = appearance
        if coat == "random" and coat_mix == "same" and bodies:
            coat = bodies[0].appearance
        elif coat == "random" and coat_mix == "different" and bodies:
            left = [c for c in coats if c not in {b.appearance for b in bodies}] or list(coats)
            coat = left[int(rng.integers(len(left)))]
        bodies.append(RatBody.random(rng, coat, float(size), coats))
    return tuple(bodies)


@dataclass(frozen=True, eq=False)
class AnimalViews:
    """Projections and visibility of every animal's keypoints in every view.

    Attributes:
        points2d: (T, C, A, K, 2) exact distorted projections, px.
        visible: (T, C, A, K) inside the image and not hidden (by any body, wall or floor).
        hidden_by_other: (T, C, A, K) hidden by another animal's body.
    """

    points2d: np.ndarray
    visible: np.ndarray
    hidden_by_other: np.ndarray


def animal_views(
    geometry: BodyGeometry, rig: CameraRig, walls: ArenaConfig | None, n_animals: int
) -> AnimalViews:
    """The :class:`AnimalViews` of the animals of ``geometry``.

    Args:
        geometry: the animals (``freipose.synth.social.combine_geometries``).
        rig: the C cameras.
        walls: the walls that hide (None: none).
        n_animals: A.
    """
    from freipose.synth.visibility import keypoint_visibility

    T, C, A, K = len(geometry), len(rig), n_animals, len(RAT_KEYPOINTS)
    other = np.zeros((T, C, A * K), bool)
    pts2d, vis = keypoint_visibility(geometry, rig, walls, hidden_by_other=other)
    return AnimalViews(
        pts2d.reshape(T, C, A, K, 2), vis.reshape(T, C, A, K), other.reshape(T, C, A, K)
    )


def write_social_labels(
    labels_path: Path,
    truth_path: Path,
    session: str,
    rig: CameraRig,
    geometry: BodyGeometry,
    motion: SocialMotion,
    walls: ArenaConfig | None,
    fps: float,
    video_format: str,
) -> None:
    """Write ``labels.h5`` (a row per frame and animal) and the truth (module docstring).

    Args:
        labels_path: the labels file.
        truth_path: the truth's poses file.
        session: the session's name.
        rig: the cameras.
        geometry: the animals over T frames.
        motion: their motion (climbs, lifts, contacts).
        walls: the walls that hide.
        fps: frame rate.
        video_format: the videos' suffix (``<camera><suffix>``).
    """
    from freipose.io.labels import LabelSet, SessionInfo, write_labels_h5
    from freipose.io.poses import PoseData, write_poses_h5

    names = animal_names(len(motion.states))
    views = animal_views(geometry, rig, walls, len(names))
    T, C, A, K = views.visible.shape
    kp = geometry.keypoints.reshape(T, A, K, 3)
    videos = {c: f"{c}{video_format}" for c in rig.names}
    labels = LabelSet(
        session=np.array([session] * (T * A), dtype=object),
        frame_index=np.repeat(np.arange(T), A),
        points2d=np.moveaxis(views.points2d, 2, 1).reshape(T * A, C, K, 2),
        points3d=kp.reshape(T * A, K, 3),
        cameras=tuple(rig.names),
        keypoints=RAT_KEYPOINTS,
        sessions={session: SessionInfo(rig, videos, fps)},
        visible2d=np.moveaxis(views.visible, 2, 1).reshape(T * A, C, K),
        individual=np.tile(np.array(names, dtype=object), T),
    )
    write_labels_h5(labels, labels_path)
    truth = PoseData(
        kp, np.ones((T, A, K), np.float32), RAT_KEYPOINTS, np.arange(T), fps,
        calibration=rig, provenance={"session": session, "source": "freipose synth truth"},
        extra={
            "points2d": np.moveaxis(views.points2d, 2, 1),
            "visible2d": np.moveaxis(views.visible, 2, 1),
            "hidden_by_animal": np.moveaxis(views.hidden_by_other, 2, 1),
            "on_top_of": motion.on_top_of.astype(np.int8),
            "lift": motion.lift.astype(np.float32),
            "contact": motion.contact,
        },
        individuals=names, identity_confidence=np.ones((T, A), np.float32),
    )  # fmt: skip
    write_poses_h5(truth, truth_path)


__all__ = [
    "TRUE_POSES_NAME",
    "AnimalViews",
    "animal_names",
    "animal_views",
    "social_bodies",
    "write_social_labels",
]
