"""Extrinsics initialisation: board poses, relative camera poses, chained over a spanning tree.

Board poses per camera, relative poses of camera pairs, chained over a maximum spanning tree
of the camera graph (edge weight = frames seen together).

Cost is O(F·C²) for the pair statistics (one robust average per pair), not FreiCalib's
O(F²·C²) frame-pair search.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from freipose.calibration.intrinsics import CalibrationError, usable_frames
from freipose.geometry.transforms import invert_transform, rodrigues_to_matrix, transform

logger = logging.getLogger(__name__)

__all__ = [
    "CameraGraph",
    "board_poses_per_camera",
    "camera_graph",
    "connected_groups",
    "initial_extrinsics",
    "mean_rotation",
]


def mean_rotation(Rs: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of rotations (N, 3, 3) -> (3, 3)."""
    M = np.asarray(Rs).sum(axis=0)
    U, _s, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def _rot_angle(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """Angle in degrees between rotations (..., 3, 3)."""
    tr = np.einsum("...ij,...ij->...", Ra, Rb)
    return np.degrees(np.arccos(np.clip((tr - 1) / 2, -1, 1)))


def board_poses_per_camera(
    points: np.ndarray,
    object_points: np.ndarray,
    K: np.ndarray,
    dist: np.ndarray,
    max_rms: float = 3.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Board→camera pose in every frame of one camera with solvePnP (IPPE + LM refinement).

    Args:
        points: (F, P, 2) detections (NaN = missing).
        object_points: (P, 3).
        K: (3, 3) intrinsic matrix.
        dist: (5,) distortion coefficients.
        max_rms: poses with a larger reprojection RMS (px) are dropped (NaN).

    Returns:
        ``(T (F, 4, 4) board→camera, NaN where unknown; rms (F,) px, NaN where unknown)``.
    """
    import cv2

    F = points.shape[0]
    T = np.full((F, 4, 4), np.nan)
    rms = np.full(F, np.nan)
    ok = usable_frames(points, object_points)
    mask = np.isfinite(points[..., 0])
    for f in np.flatnonzero(ok):
        m = mask[f]
        obj = object_points[m].astype(np.float64)
        img = points[f, m].astype(np.float64)
        good, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
        if not good:
            continue
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
        proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
        e = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))
        if e > max_rms or float(np.asarray(tvec).reshape(3)[2]) <= 0:
            continue
        T[f] = transform(rodrigues_to_matrix(rvec), tvec)
        rms[f] = e
    return T, rms


@dataclass(frozen=True)
class CameraGraph:
    """Pairwise statistics of the cameras' board poses.

    Attributes:
        names: the camera names.
        shared: (C, C) frames where cameras i and j both have a board pose.
        relative: (C, C, 4, 4) robust average of T_i←j (camera j → camera i), NaN if unknown.
        tree_edges: the spanning tree's edges ``(i, j)`` (camera j chained from camera i).
        root: the index of the camera whose frame is the world.
    """

    names: tuple[str, ...]
    shared: np.ndarray
    relative: np.ndarray
    tree_edges: tuple[tuple[int, int], ...] = ()
    root: int = 0

    def to_dict(self) -> dict:
        """The graph as plain data (cameras, shared frames per pair, spanning tree, root)."""
        n = len(self.names)
        return {
            "cameras": list(self.names),
            "shared_frames": {
                f"{self.names[i]}-{self.names[j]}": int(self.shared[i, j])
                for i in range(n)
                for j in range(i + 1, n)
                if self.shared[i, j] > 0
            },
            "spanning_tree": [[self.names[i], self.names[j]] for i, j in self.tree_edges],
            "root": self.names[self.root],
        }


def _relative_pose(Ti: np.ndarray, Tj: np.ndarray) -> tuple[np.ndarray, int]:
    """Robust mean of T_i←j = Ti · Tj⁻¹ over frames (N, 4, 4); returns (T, inliers)."""
    Rs = Ti[:, :3, :3] @ np.transpose(Tj[:, :3, :3], (0, 2, 1))
    ts = Ti[:, :3, 3] - np.einsum("nij,nj->ni", Rs, Tj[:, :3, 3])
    R0 = mean_rotation(Rs)
    t0 = np.median(ts, axis=0)
    for _ in range(3):
        ang = _rot_angle(Rs, R0[None])
        dt = np.linalg.norm(ts - t0, axis=1)
        s_ang = max(1.4826 * np.median(ang), 0.5)
        s_t = max(1.4826 * np.median(dt), 1e-3 * (np.linalg.norm(t0) + 1.0))
        inl = (ang < 3 * s_ang) & (dt < 3 * s_t)
        if inl.sum() < max(1, len(Rs) // 4):
            inl = ang <= np.median(ang)
        R0 = mean_rotation(Rs[inl])
        t0 = np.mean(ts[inl], axis=0)
    return transform(R0, t0), int(inl.sum())


def camera_graph(names: Sequence[str], poses: np.ndarray) -> CameraGraph:
    """Pair statistics from board poses (C, F, 4, 4) board→camera (NaN = unknown)."""
    C = len(names)
    have = np.isfinite(poses[:, :, 0, 0])  # (C, F)
    shared = (have[:, None, :] & have[None, :, :]).sum(axis=2)
    np.fill_diagonal(shared, 0)
    rel = np.full((C, C, 4, 4), np.nan)
    for i in range(C):
        rel[i, i] = np.eye(4)
        for j in range(i + 1, C):
            both = have[i] & have[j]
            if not both.any():
                continue
            T, _n = _relative_pose(poses[i, both], poses[j, both])
            rel[i, j] = T
            rel[j, i] = invert_transform(T)
    return CameraGraph(tuple(names), shared, rel)


def connected_groups(shared: np.ndarray, min_shared: int = 1) -> list[list[int]]:
    """Connected components of the camera graph (edges with >= min_shared frames)."""
    C = shared.shape[0]
    seen = [False] * C
    groups = []
    for s in range(C):
        if seen[s]:
            continue
        stack, comp = [s], []
        seen[s] = True
        while stack:
            u = stack.pop()
            comp.append(u)
            for v in range(C):
                if not seen[v] and shared[u, v] >= min_shared:
                    seen[v] = True
                    stack.append(v)
        groups.append(sorted(comp))
    return groups


def initial_extrinsics(
    names: Sequence[str], poses: np.ndarray, min_shared: int = 2
) -> tuple[np.ndarray, CameraGraph]:
    """World→camera transforms in the root camera's frame, chained over a spanning tree.

    The tree is the maximum spanning tree of the camera graph (edge weight = shared frames).

    Args:
        names: camera names.
        poses: (C, F, 4, 4) board→camera poses, NaN where unknown.
        min_shared: frames two cameras must share to be connected.

    Returns:
        ``(T_world (C, 4, 4) world→camera, the camera graph with its spanning tree)``.

    Raises:
        CalibrationError: the cameras do not form one connected group (names the groups).
    """
    graph = camera_graph(names, poses)
    C = len(names)
    groups = connected_groups(graph.shared, min_shared)
    if len(groups) > 1:
        desc = "; ".join("{" + ", ".join(names[i] for i in g) + "}" for g in groups)
        raise CalibrationError(
            f"the cameras do not all see the board together (at least {min_shared} common "
            f"frames per link): connected groups are {desc}. Record frames in which the board is "
            f"visible to cameras of different groups at the same time"
        )
    # root: the camera with the most shared frames overall
    root = int(np.argmax(graph.shared.sum(axis=1))) if C > 1 else 0
    # Prim's maximum spanning tree
    in_tree = np.zeros(C, bool)
    in_tree[root] = True
    edges: list[tuple[int, int]] = []
    T_world = np.full((C, 4, 4), np.nan)  # world (= root camera) → camera
    T_world[root] = np.eye(4)
    while not in_tree.all():
        w = np.where(in_tree[:, None] & ~in_tree[None, :], graph.shared, -1)
        i, j = np.unravel_index(np.argmax(w), w.shape)
        if w[i, j] < min_shared:  # pragma: no cover - excluded by the component check
            raise CalibrationError("camera graph is disconnected")
        # T_j←world = T_j←i · T_i←world
        T_world[j] = graph.relative[j, i] @ T_world[i]
        in_tree[j] = True
        edges.append((int(i), int(j)))
    graph = CameraGraph(graph.names, graph.shared, graph.relative, tuple(edges), root)
    return T_world, graph


def initial_board_poses(T_world: np.ndarray, poses: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Board→world per frame (F, 4, 4) from the camera that sees most points (NaN if none).

    Args:
        T_world: (C, 4, 4) world→camera.
        poses: (C, F, 4, 4) board→camera (NaN = unknown).
        counts: (C, F) detected points.
    """
    C, F = poses.shape[:2]
    have = np.isfinite(poses[:, :, 0, 0])
    score = np.where(have, counts, -1)
    best = np.argmax(score, axis=0)
    out = np.full((F, 4, 4), np.nan)
    for f in range(F):
        c = best[f]
        if have[c, f]:
            out[f] = invert_transform(T_world[c]) @ poses[c, f]
    return out
