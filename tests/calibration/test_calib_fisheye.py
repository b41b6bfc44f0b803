"""A synthetic mouse rig with fisheye-like lenses calibrates without --force."""

from __future__ import annotations

import numpy as np
import pytest
from calib_helpers import rig_errors
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.io.calibration import load_calibration


def test_fisheye_mouse_rig_calibrates(tmp_path):
    pytest.importorskip("freipose.synth.board")
    runner = CliRunner()
    rec = tmp_path / "rec"
    # the own-data rig (docs/own-data.md) with strong fisheye distortion; in this scene the
    # board stays near the top of camera cam2's image, and the fitted k1 k2 fold beyond it
    synth = (
        f"synth {rec} --animal mouse --arena-size 250x250 --wall-height 120 --cameras 4 "
        f"--grayscale --lens fisheye --frames 2 --calibration-video --calibration-frames 100"
    )
    res = runner.invoke(cli, synth.split())
    assert res.exit_code == 0, res.output
    cal = rec / "calibration"
    out = tmp_path / "calibration.toml"
    args = ["calib", *sorted(str(p) for p in cal.glob("cam*.mp4")), "--board"]
    args += [str(cal / "board.toml"), "--origin-frame", "0", "-o", str(out)]
    args += ["--report", str(tmp_path / "report")]
    res = runner.invoke(cli, args)
    assert res.exit_code == 0, res.output
    assert "folds" in res.output and "image points farther out" in res.output  # warned
    assert (tmp_path / "report" / "coverage_cam2.png").is_file()
    est = load_calibration(out)
    assert "suspect" not in est.metadata
    truth = load_calibration(rec / "true_calibration.toml")
    dc, rot, fe = rig_errors(est, truth)
    assert dc.max() < 3.0, dc  # mm, cameras 340-620 mm away
    assert rot.max() < 3.0, rot  # deg (320x256 images, f 200-300 px)
    assert np.abs(fe).max() < 2.0, fe  # %
    for cam, true in zip(est, truth):
        assert abs(cam.dist[0] - true.dist[0]) < 0.1, (cam.name, cam.dist, true.dist)
