"""A camera whose corners are honestly noisier than the others' calibrates without --force.

The outlier threshold follows each camera's own noise level, so such a camera keeps its
detections (and the rig stays as accurate as an ordinary one), while corners with wrong
ids are still removed.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from calib_helpers import board_detections, rig_errors

from freipose.calibration.boards import CharucoBoard
from freipose.calibration.options import CalibrationOptions
from freipose.calibration.pipeline import calibrate_detections
from freipose.testing import make_circle_rig

BOARD = CharucoBoard(8, 6, 40.0, 30.0, "DICT_4X4_50")
OPT = CalibrationOptions(progress=False)


@pytest.fixture(scope="module")
def rig():
    return make_circle_rig(4, radius=700.0, height=400.0, distortion=True)


@pytest.fixture(scope="module")
def dets(rig):
    return board_detections(rig, BOARD.object_points, BOARD.size_mm, 80, noise_px=0.1)[0]


@pytest.fixture(scope="module")
def ordinary(rig, dets):
    """The worst centre, rotation and focal errors of the recording as it is."""
    return _worst(calibrate_detections(dets, BOARD, OPT), rig)


def _noisier(dets, camera: int, scale: float = 0.45):
    """``camera``'s corners with heavy-tailed noise (Student t, 4 dof) of ``scale`` px added."""
    d = dets[camera]
    p = d.points.copy()
    m = np.isfinite(p[..., 0])
    p[m] += scale * np.random.default_rng(1).standard_t(4, (int(m.sum()), 2))
    out = list(dets)
    out[camera] = dataclasses.replace(d, points=p)
    return out


def _worst(res, truth):
    dc, rot, fe = rig_errors(res.rig, truth)
    return float(dc.max()), float(rot.max()), float(np.abs(fe).max())


def test_noisier_camera_keeps_its_detections_and_the_rig_its_accuracy(rig, dets, ordinary):
    noisy = _noisier(dets, 1)
    res = calibrate_detections(noisy, BOARD, OPT)  # a global threshold rejected 60 %: refused
    ba = res.bundle
    mine = ba.obs.cam == 1
    assert np.mean(~ba.inliers[mine]) < 0.08  # heavy tails only
    assert res.findings == ()
    c, r, f = _worst(res, rig)
    c0, r0, f0 = ordinary
    # as accurate as the ordinary recording, up to what the noisier camera's noise costs
    assert c < max(2 * c0, 1.0) and r < max(2 * r0, 0.1) and f < max(2 * f0, 0.3)


def test_camera_with_blurred_views_is_not_refused(rig, dets, ordinary):
    """40 % of a camera's views blurred (1.5 px noise): the 2 px floor keeps most of them."""
    d = dets[1]
    p = d.points.copy()
    rng = np.random.default_rng(3)
    frames = np.flatnonzero(np.isfinite(p[..., 0]).any(1))
    for f in rng.choice(frames, int(0.4 * frames.size), replace=False):
        m = np.isfinite(p[f, :, 0])
        p[f, m] += rng.normal(0, 1.5, (int(m.sum()), 2))
    blurred = list(dets)
    blurred[1] = dataclasses.replace(d, points=p)
    res = calibrate_detections(blurred, BOARD, OPT)  # a 0.5 px floor rejected 34 %: refused
    assert res.findings == ()
    c, r, f = _worst(res, rig)
    c0, r0, f0 = ordinary
    assert c < max(2 * c0, 1.0) and r < max(2 * r0, 0.1) and f < max(2 * f0, 0.3)


def test_wrong_ids_are_removed(rig, dets):
    noisy = _noisier(dets, 1)
    d = noisy[1]
    p = d.points.copy()
    frames = np.flatnonzero(np.isfinite(p[..., 0]).sum(1) >= 6)
    bad = frames[::7]  # every 7th view: each corner takes its neighbour's id
    for f in bad:
        m = np.flatnonzero(np.isfinite(p[f, :, 0]))
        p[f, m] = p[f, np.roll(m, 1)]
    noisy[1] = dataclasses.replace(d, points=p)
    res = calibrate_detections(noisy, BOARD, OPT)
    ba = res.bundle
    mine = np.flatnonzero(ba.obs.cam == 1)
    obs_wrong = np.isin(ba.frames[ba.obs.frame[mine]], bad)
    assert obs_wrong.sum() > 100
    assert np.mean(~ba.inliers[mine][obs_wrong]) > 0.95  # removed
    assert np.mean(~ba.inliers[mine][~obs_wrong]) < 0.08  # the right ones kept
    c, r, f = _worst(res, rig)
    assert c < 1.5 and r < 0.15 and f < 0.5
