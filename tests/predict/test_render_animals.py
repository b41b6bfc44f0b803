"""``freipose render`` of poses with an animal axis: every animal in its own colour."""

from __future__ import annotations

import numpy as np
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.io.poses import read_poses_h5
from freipose.io.video import FrameSource
from freipose.predict.render import ANIMAL_COLOURS, render_stills


def _count(img: np.ndarray, bgr: tuple[int, int, int]) -> int:
    return int(np.all(np.abs(img.astype(int) - bgr) <= 2, axis=-1).sum())


def test_render_colours_each_animal(tmp_path):
    sess = tmp_path / "pair"
    r = CliRunner().invoke(
        cli,
        ["synth", str(sess), "--animals", "2", "--frames", "4", "--cameras", "2", "--size",
         "160x128", "--seed", "4", "--lossless"],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    truth = sess / "true_poses.h5"
    out = tmp_path / "overlay.mkv"
    r = CliRunner().invoke(cli, ["render", str(sess), str(truth), "-o", str(out)])
    assert r.exit_code == 0, r.output
    with FrameSource(out) as src:
        frame = src.read(2)
    n0, n1 = (_count(frame, ANIMAL_COLOURS[a]) for a in range(2))
    assert n0 > 30 and n1 > 30, (n0, n1)
    data = read_poses_h5(truth)
    stills = render_stills(
        [sess / "cam0.mkv", sess / "cam1.mkv"], data.calibration, data, [1], [tmp_path / "s.png"]
    )
    import cv2

    img = cv2.imread(str(stills[0]))
    assert all(_count(img, ANIMAL_COLOURS[a]) > 30 for a in range(2))
