"""Several animals on rendered frames: background subtraction, association, tracking."""

from __future__ import annotations

import numpy as np
import pytest

from freipose.detect import BackgroundSubtractor
from freipose.detect.multi import SplitForeground
from freipose.predict.animals import score_tracks, track_recording


@pytest.mark.slow
def test_two_rendered_rats_are_detected_and_followed(tmp_path):
    """A 25 s synthetic pair (4 cameras, 6 fps so the background is learnt from few frames)."""
    synth = pytest.importorskip("freipose.synth")
    from freipose.io.calibration import load_calibration
    from freipose.io.poses import read_poses_h5
    from freipose.io.video import FrameSource

    cfg = synth.SceneConfig(frames=150, fps=6, seed=3, n_cameras=4, size=(256, 208), animals=2,
                            coat_mix="different")  # fmt: skip
    paths = synth.generate_session(tmp_path / "pair", cfg, workers=1, progress=False)
    rig = load_calibration(paths.calibration)
    truth = read_poses_h5(paths.truth)
    src = [FrameSource(paths.videos[n]) for n in rig.names]
    frames = [[s.read(t) for s in src] for t in range(150)]
    bg = BackgroundSubtractor.fit({n: [f[i] for f in frames] for i, n in enumerate(rig.names)})
    arena = np.array([[-300.0, 300], [-300, 300], [-20, 250]])
    res = track_recording(frames, rig, SplitForeground(bg, 2), 2, truth.fps, bounds=arena)
    s = score_tracks(res, truth.extra["points2d"], truth.extra["visible2d"], rig)
    # measured on this scene: 0 switches, candidate recall 0.76 / 0.83, followed 0.91 / 0.93,
    # median centre error 16 mm
    assert s.switches <= 1, s
    assert min(s.recall_boxes) >= 0.6 and min(s.followed) >= 0.8, s
    assert s.center_error_mm < 30, s
    assert res.tracks.centers.shape == (150, 2, 3) and res.tracks.boxes.shape == (150, 2, 4, 4)
