"""The voxel cube sized from the training labels (``[model] cube_size = "auto"`` or absent)."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from nn_toydata import toy_samples, write_toy_labels

from freipose.io.labels import LabelSet, SessionInfo
from freipose.nn.checkpoint import read_checkpoint
from freipose.nn.config import ConfigError, config_from_dict
from freipose.nn.sizing import SizingError, animal_radius, resolve_cube, size_cube
from freipose.testing import make_circle_rig


def _labels(radius: float, n: int = 100) -> LabelSet:
    """Instants of a 'star' animal: four keypoints at ``radius`` around a moving centre."""
    star = np.array([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]]) * radius
    centres = np.stack([np.linspace(-100, 100, n), np.zeros(n), np.full(n, 50.0)], -1)
    p3 = centres[:, None] + star[None]
    p3[0, :2] = np.nan  # a partly labeled instant still counts (two keypoints left)
    p3[1, 1:] = np.nan  # one keypoint: no radius
    rig = make_circle_rig(3, radius=800, height=500, size=(320, 240), focal=300)
    return LabelSet(
        np.array(["s"] * n, dtype=object), np.arange(n), np.full((n, 3, 4, 2), np.nan), p3,
        tuple(rig.names), ("a", "b", "c", "d"), {"s": SessionInfo(rig, {}, 50.0)},
    )  # fmt: skip


def test_radius_and_cube_from_the_labels():
    lab = _labels(radius=48.0)
    r, n = animal_radius(lab.points3d)
    assert n == 99 and r == pytest.approx(48.0)
    cfg = config_from_dict({"model": {"preset": "small"}})
    s = size_cube(lab, cfg.model)
    assert s.cube_size == 120.0  # 2 * 48 * 1.25 = 120
    assert s.voxel_size == pytest.approx(120.0 / 31)
    assert s.crop_cube == pytest.approx(0.6 * 120.0)  # the small preset's crop_fraction
    # the crop cube's projection: about focal * edge / depth pixels (corners make it wider)
    assert 300 * 72 / 950 < s.crop_pixels < 2 * 300 * 72 / 950
    assert size_cube(_labels(radius=49.0), cfg.model).cube_size == 130.0  # rounded up
    with pytest.raises(SizingError, match="model.cube_size"):
        size_cube(lab.select([1]), cfg.model)


def test_auto_absent_and_explicit(caplog):
    lab = _labels(radius=48.0)
    absent = config_from_dict({"model": {"preset": "small"}})
    auto = config_from_dict({"model": {"preset": "small", "cube_size": "auto"}})
    explicit = config_from_dict({"model": {"preset": "small", "cube_size": 250}})
    assert absent.cube_auto and auto.cube_auto and not explicit.cube_auto
    with caplog.at_level(logging.INFO, logger="freipose.nn.sizing"):
        got = resolve_cube(auto, lab)
    assert got.model.cube_size == 120.0 and not got.cube_auto
    assert "cube 120 mm from the training labels" in caplog.text and "radius" in caplog.text
    assert resolve_cube(explicit, lab).model.cube_size == 250.0  # an explicit number wins
    with pytest.raises(ConfigError, match="cube_size must be a number"):
        config_from_dict({"model": {"cube_size": "big"}})


def test_train_command_stores_the_chosen_cube(tmp_path):
    from click.testing import CliRunner

    from freipose.cli.main import cli

    labels = write_toy_labels(tmp_path / "data", toy_samples(3))
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(
        f'[data]\nlabels = "{labels}"\n[model]\npreset = "tiny"\n'
        "[schedule]\nsteps = 1\ncheckpoint_every = 1\neval_every = 1\n"
    )
    res = CliRunner().invoke(cli, ["-q", "train", str(cfg), "--out", str(tmp_path / "run")])
    assert res.exit_code == 0, res.output
    ckpt = read_checkpoint(tmp_path / "run" / "model.pt")
    from freipose.io.labels import read_labels_h5

    expect = size_cube(
        read_labels_h5(labels), config_from_dict({"model": {"preset": "tiny"}}).model
    )
    assert ckpt["config"]["model"]["cube_size"] == expect.cube_size != 400.0
    assert f"cube_size = {expect.cube_size}" in (tmp_path / "run" / "config.toml").read_text()
