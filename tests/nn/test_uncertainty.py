"""The raw uncertainty: the views' and P0-P1's disagreement, per sample and per batch."""

from __future__ import annotations

import numpy as np
import pytest

from freipose.geometry.camera import Camera, CameraRig
from freipose.nn.uncertainty import raw_uncertainty, view_disagreement

K0 = np.array([[1000.0, 0.0, 0.0], [0.0, 1000.0, 0.0], [0.0, 0.0, 1.0]])


def _rig(n: int, dist: float = 0.0) -> CameraRig:
    """n cameras at the origin looking along +z (the same camera, n times)."""
    d = np.array([dist, 0.0, 0.0, 0.0, 0.0])
    return CameraRig(tuple(Camera(f"c{i}", (640, 480), K0, d) for i in range(n)))


def test_view_disagreement_is_the_weighted_rms_distance_from_the_rays():
    P = np.array([[0.0, 0.0, 1000.0]])
    # view 0 sees the point 10 px to the right: its ray passes 10 mm away at 1 m depth;
    # view 1 sees it exactly
    uv = np.array([[[10.0, 0.0]], [[0.0, 0.0]]])
    conf = np.array([[0.25], [0.75]])
    got = view_disagreement(P, uv, conf, _rig(2))
    assert got == pytest.approx([np.sqrt(0.25 * 100 + 0.75 * 0)], rel=1e-12)
    u = raw_uncertainty(P[None] + [3.0, 0, 0], P[None], uv[None], conf[None], [_rig(2)], 2.0)
    assert u[0] == pytest.approx([np.sqrt(25 + 9 + 1)], rel=1e-9)


def test_a_batch_equals_its_samples_one_by_one():
    """Samples sharing a rig are computed together, with other rigs and padding views."""
    rng = np.random.default_rng(0)
    shared, other = _rig(3, dist=-0.1), _rig(2, dist=0.05)
    rigs = [shared, other, shared, shared, other]
    B, V, K = len(rigs), 3, 4
    P1 = rng.normal([0, 0, 1000], 20, (B, K, 3))
    P0 = P1 + rng.normal(0, 2, (B, K, 3))
    uv = rng.normal(0, 40, (B, V, K, 2))
    uv[1, 2] = uv[4, 2] = np.nan  # padding view of the 2-camera rig
    uv[0, 1, 2] = np.nan  # a view without this keypoint
    conf = rng.uniform(0, 1, (B, V, K))
    P1[3, 1] = np.nan  # an unknown point
    batch = raw_uncertainty(P0, P1, uv, conf, rigs, 2.0)
    for b, rig in enumerate(rigs):
        one = raw_uncertainty(P0[b : b + 1], P1[b : b + 1], uv[b : b + 1], conf[b : b + 1],
                              [rig], 2.0)  # fmt: skip
        np.testing.assert_allclose(batch[b], one[0], rtol=1e-12)
    assert np.isnan(batch[3, 1]) and np.isfinite(np.delete(batch.ravel(), 3 * K + 1)).all()
