"""Background subtraction on a truncated video: the frames that cannot be decoded get no
box and the others go on, in ``freipose detect`` and in ``freipose predict --method
bgsub`` (whose background model is fitted on the readable frames)."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import small_rig, write_session

from freipose.cli.main import cli
from freipose.io.boxes import read_boxes_h5
from freipose.io.session import discover_sessions

N = 16


@pytest.fixture(scope="module")
def truncated(tmp_path_factory):
    """A session whose cam2.mkv is cut in half (its last frames cannot be decoded)."""
    folder = tmp_path_factory.mktemp("trunc") / "s"
    write_session(folder, small_rig(), N, seed=5)
    vid = folder / "cam2.mkv"
    data = vid.read_bytes()
    vid.write_bytes(data[: len(data) // 2])
    return folder


def test_detect_bgsub_marks_undecodable_frames_and_goes_on(truncated, tmp_path, caplog):
    out = tmp_path / "boxes.h5"
    with caplog.at_level(logging.WARNING):
        res = CliRunner().invoke(
            cli, ["detect", str(truncated), "--method", "bgsub", "-o", str(out)]
        )
    assert res.exit_code == 0, res.output
    log = caplog.text + res.output  # the CLI's own log handler writes to its stderr
    assert "camera 'cam2': frames from 7 on cannot be decoded" in log
    d = read_boxes_h5(out)
    assert len(d) == N
    bad = np.isnan(d.boxes[:, 2]).any(-1)
    gap = int(np.argmax(bad))
    assert 0 < gap < N and bad[gap:].all() and not bad[:gap].any()
    assert np.isnan(d.crop_boxes[gap:, 2]).all() and not d.agree[gap:, 2].any()
    # the other three cameras agree in every frame, before and after the gap
    assert d.agree[:, [0, 1, 3]].all() and (d.n_agree[gap:] == 3).all()
    assert np.isfinite(d.center).all()


def test_predict_bgsub_fits_on_the_readable_frames(truncated, caplog):
    from freipose.predict.network import DetectorSpec, make_box_source

    (s,) = discover_sessions([truncated], cameras="calibration", need_fps=False)
    with caplog.at_level(logging.WARNING):
        source = make_box_source(DetectorSpec("bgsub"), s, (0, N), "cpu")
    assert "cannot be decoded" in caplog.text
    from freipose.io.video import FrameSource

    with FrameSource(truncated / "cam2.mkv") as src:
        img = src.read(0)
    (cands,) = source.propose([img], ["cam2"])
    assert len(cands) > 0
