"""A rendered recording like a real handheld one that a global outlier threshold refused.

Strong (fisheye) distortion, a board printed inverted and seen through (transparent), one
camera below the floor that sees it from behind in every frame, ring cameras that see it
partly and sometimes from behind; that camera's corners carry heavy-tailed noise of about
0.6 px median (what the real recording's camera showed, against 0.15 px elsewhere). With the
threshold of one noise level for all cameras it lost 61 % of its detections and was refused,
and with --force it was 2.6 degrees off; with each camera's own noise level it calibrates
without --force, as accurately as the same recording without the extra noise.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from calib_helpers import rig_errors


def _worst(res, truth) -> tuple[float, float, float]:
    dc, rot, fe = rig_errors(res.rig, truth)
    return float(dc.max()), float(rot.max()), float(np.abs(fe).max())


@pytest.mark.slow
def test_rendered_hard_recording_calibrates_without_force(tmp_path):
    synth_board = pytest.importorskip("freipose.synth.board")
    from freipose.calibration.detect_videos import detect_cameras
    from freipose.calibration.options import CalibrationOptions
    from freipose.calibration.pipeline import calibrate_detections
    from freipose.synth.rig import default_rig

    rig = default_rig(4, size=(480, 270), lens="fisheye", layout="below")
    board = dataclasses.replace(synth_board.default_board(), inverted=True)
    vids, _ = synth_board.write_board_videos(
        tmp_path, rig, board, 80, seed=0, progress=False, transparent=True, workers=2
    )
    dets = detect_cameras([vids[n] for n in rig.names], board, cache_dir=None, jobs=2)
    below = dets[-1]
    assert below.back_views == int((below.counts >= 4).sum()) > 40  # always from behind
    assert sum(d.back_views for d in dets[:-1]) > 0  # ring cameras: partly from behind
    opt = CalibrationOptions(jobs=1, progress=False)
    ordinary = calibrate_detections(dets, board, opt)
    p = below.points.copy()
    m = np.isfinite(p[..., 0])
    p[m] += 0.45 * np.random.default_rng(1).standard_t(4, (int(m.sum()), 2))
    noisy = [*dets[:-1], dataclasses.replace(below, points=p)]
    res = calibrate_detections(noisy, board, opt)  # raises ImplausibleCalibrationError if refused
    assert res.findings == ()
    ba = res.bundle
    mine = ba.obs.cam == len(rig) - 1
    assert np.median(ba.errors[mine & ba.inliers]) > 0.4  # the noise is there ...
    assert np.mean(~ba.inliers[mine]) < 0.08  # ... and the corners are kept
    c, r, f = _worst(res, rig)
    c0, r0, f0 = _worst(ordinary, rig)
    assert c < max(2 * c0, 2.0) and r < max(2 * r0, 0.1) and f < max(2 * f0, 0.5), (
        (c, r, f),
        (c0, r0, f0),
    )
