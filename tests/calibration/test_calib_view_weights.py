"""Per-view noise weighting of the bundle adjustment (``--view-weights``)."""

from __future__ import annotations

import numpy as np
from calib_helpers import board_detections, rig_errors

from freipose.calibration.boards import CharucoBoard
from freipose.calibration.detect import CameraDetections
from freipose.calibration.options import CalibrationOptions
from freipose.calibration.pipeline import calibrate_detections
from freipose.calibration.robust import view_noise_scales
from freipose.testing import make_circle_rig

BOARD = CharucoBoard(6, 5, 40.0, 30.0, "DICT_4X4_50")


def test_view_noise_scales_follow_each_views_noise():
    rng = np.random.default_rng(0)
    sig = np.array([0.1, 0.1, 0.3, 0.05])  # per-axis noise of 4 views, 200 points each
    groups = np.repeat(np.arange(4), 200)
    err = np.linalg.norm(rng.normal(0, 1, (800, 2)), axis=1) * sig[groups]
    s = view_noise_scales(err, groups, sigma=0.1, prior_count=0.0)
    per_view = np.array([s[groups == g][0] for g in range(4)])
    # the quiet view is not up-weighted (clipped at 1)
    assert np.allclose(per_view, [1.0, 1.0, 1 / 3, 1.0], rtol=0.15)
    assert np.all(s == per_view[groups])
    # few points per view: shrunk towards 1 (the global level), and clipped at 0.25
    few = view_noise_scales(err[groups == 2][:3], np.zeros(3, int), sigma=0.1, prior_count=8)
    assert 1 / 3 < few[0] < 1.0
    loud = view_noise_scales(np.full(50, 10.0), np.zeros(50, int), sigma=0.1, prior_count=0)
    assert np.allclose(loud, 0.25)
    # observations not used for the estimate (rejected) get their view's scale; a view with
    # none used gets 1
    use = groups != 3
    use[groups == 2] = np.arange(200) % 2 == 0
    part = view_noise_scales(err, groups, sigma=0.1, prior_count=0.0, use=use)
    assert np.all(part[groups == 3] == 1.0)
    assert np.ptp(part[groups == 2]) == 0 and part[groups == 2][0] < 0.5


def test_noisy_views_count_less():
    # a quarter of the board views are 5x noisier than the rest (motion blur): weighting every
    # view by its own noise level recovers the rig better than equal weights
    rig = make_circle_rig(4, radius=700.0, height=400.0, distortion=True)
    dets, _ = board_detections(rig, BOARD.object_points, BOARD.size_mm, 120, noise_px=0.1, seed=3)
    rng = np.random.default_rng(5)
    noisy = []
    for d in dets:
        pts = d.points.copy()
        blur = rng.random(len(pts)) < 0.25
        pts[blur] += rng.normal(0, 0.4, pts[blur].shape)  # on top of the 0.1 px
        noisy.append(CameraDetections(d.name, d.size, pts))
    opts = dict(refine_board=False, outlier_px=3.0)  # keep the noisy views in
    w = calibrate_detections(noisy, BOARD, CalibrationOptions(**opts))
    u = calibrate_detections(noisy, BOARD, CalibrationOptions(view_weights=False, **opts))
    assert w.bundle.view_scale is not None and u.bundle.view_scale is None
    assert w.rig.metadata["view_weights"] is True and u.rig.metadata["view_weights"] is False
    dc_w, rot_w, fe_w = rig_errors(w.rig, rig)
    dc_u, rot_u, fe_u = rig_errors(u.rig, rig)
    # RMS over cameras, measured: centres 0.17 vs 0.27 mm, rotations 0.013 vs 0.027 deg,
    # focal lengths 0.023 vs 0.075 %
    assert np.sqrt(np.mean(dc_w**2)) < 0.9 * np.sqrt(np.mean(dc_u**2))
    assert np.sqrt(np.mean(rot_w**2)) < 0.7 * np.sqrt(np.mean(rot_u**2))
    assert np.sqrt(np.mean(fe_w**2)) < 0.6 * np.sqrt(np.mean(fe_u**2))
    # the noisy views got the low weights
    s = w.bundle.view_scale[w.bundle.inliers]
    assert np.median(s) > 0.9 and np.percentile(s, 10) < 0.5


def test_view_weights_follow_their_observations_in_any_order():
    # the solver sorts observations by camera and frame internally: view scales (and the
    # covariance's weights) must be permuted with them
    from freipose.calibration.bundle import bundle_adjust, camera_covariance
    from freipose.calibration.bundle_problem import Observations

    rig = make_circle_rig(3, radius=700.0, height=400.0, distortion=True)
    dets, _ = board_detections(rig, BOARD.object_points, BOARD.size_mm, 40, noise_px=0.1, seed=1)
    ba = calibrate_detections(dets, BOARD, CalibrationOptions(refine_board=False)).bundle
    rng = np.random.default_rng(0)
    scale = rng.uniform(0.3, 1.0, len(ba.obs))
    free = np.zeros_like(ba.cam_params, bool)
    free[1:, 9:] = True
    perm = rng.permutation(len(ba.obs))
    o = ba.obs
    shuffled = Observations(o.cam[perm], o.frame[perm], o.point[perm], o.uv[perm])
    kw = dict(f_scale=0.2, max_rounds=1)
    a = bundle_adjust(ba.cam_params, free, ba.frame_params, ba.frames, o, view_scale=scale, **kw)
    b = bundle_adjust(
        ba.cam_params, free, ba.frame_params, ba.frames, shuffled, view_scale=scale[perm], **kw
    )
    np.testing.assert_allclose(a.cam_params, b.cam_params, atol=1e-6)
    np.testing.assert_allclose(camera_covariance(a, free), camera_covariance(b, free), rtol=1e-6)
