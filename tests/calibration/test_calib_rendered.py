"""End to end on rendered board videos (the project's one board renderer, freipose.synth)."""

from __future__ import annotations

import numpy as np
import pytest
from calib_helpers import rig_errors


@pytest.mark.slow
def test_rendered_charuco_rig(tmp_path):
    synth_board = pytest.importorskip("freipose.synth.board")
    from freipose.calibration.board_files import load_board
    from freipose.calibration.options import CalibrationOptions
    from freipose.calibration.pipeline import calibrate
    from freipose.io.calibration import load_calibration
    from freipose.synth.rig import default_rig

    # small and short to stay fast: 4 distorted 320x240 cameras, 90 frames, sensor noise.
    # (At 640x480 and 150 frames the errors are about 0.06-0.24 mm, 0.01-0.03 deg,
    # 0.04-0.08 %; see benchmarks/calibration.py.)
    rig = default_rig(4, size=(320, 240))
    board = synth_board.default_board()
    vids, _ = synth_board.write_board_videos(tmp_path, rig, board, 90, seed=0, progress=False)
    truth = load_calibration(tmp_path / "true_calibration.toml")
    assert load_board(tmp_path / "board.toml") == board
    res = calibrate(
        [vids[n] for n in rig.names],
        board,
        tmp_path / "out.toml",
        CalibrationOptions(jobs=1, progress=False),
    )
    dc, rot, fe = rig_errors(res.rig, truth)
    assert dc.max() < 8.0, dc
    assert rot.max() < 4.0, rot  # 320x240 at f ~ 275 px: 1 px of principal point ~ 0.2 deg
    assert np.abs(fe).max() < 2.0, fe
    assert all(s.rms < 0.5 for s in res.stats)
    # with the board on the floor in frame 0 the floor is z = 0 and the cameras are above it
    res0 = calibrate(
        [vids[n] for n in rig.names],
        board,
        tmp_path / "out.toml",
        CalibrationOptions(jobs=1, progress=False, origin_frame=0),
    )
    assert (res0.rig.centers[:, 2] > 100).all()
    z_true = truth.centers[:, 2]
    assert np.abs(res0.rig.centers[:, 2] - z_true).max() < 15.0
