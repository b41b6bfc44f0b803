"""Starting weights of a detector training: [detector] init = base | scratch | a path."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import torch

import freipose.models as models
from freipose.detect.detector import save_checkpoint
from freipose.detect.init import DetectorInitError, initialize_detector
from freipose.detect.model import DetectorConfig, DetectorNet
from freipose.detect.train import DetectorTrainConfig, ViewImages, fit

ARCH = DetectorConfig(input_size=64, width=0.25, neck_channels=8)


@pytest.fixture
def shipped(tmp_path, monkeypatch):
    """A package-data folder shipping a detector of width 0.25, neck 8 (other input size)."""
    torch.manual_seed(1)
    net = DetectorNet(DetectorConfig(input_size=96, width=0.25, neck_channels=8))
    save_checkpoint(tmp_path / "detector_tiny.pt", net, extra={"step": 7})
    entry = {
        "name": "detector",
        "kind": "detector",
        "file": "detector_tiny.pt",
        "architecture": net.config.to_dict(),
        "steps": 7,
    }
    (tmp_path / "bases.json").write_text(json.dumps({"bases": [entry]}))
    monkeypatch.setattr(models, "_root", lambda: tmp_path)
    return net.state_dict()


def test_base_detector_fits_any_input_size(shipped, caplog):
    net = DetectorNet(ARCH)
    with caplog.at_level(logging.INFO, logger="freipose.detect.init"):
        assert initialize_detector(net, "base") == "base:detector"
    torch.testing.assert_close(net.state_dict(), shipped)
    assert "starting from base:detector (step 7)" in caplog.text


def test_no_base_detector_warns_and_keeps_scratch(shipped, caplog):
    net = DetectorNet(DetectorConfig(input_size=64, width=0.5, neck_channels=8))
    before = {k: v.clone() for k, v in net.state_dict().items()}
    with caplog.at_level(logging.WARNING, logger="freipose.detect.init"):
        assert initialize_detector(net, "base") == "scratch"
    torch.testing.assert_close(net.state_dict(), before)
    assert "no base detector is shipped for width 0.5" in caplog.text
    assert initialize_detector(DetectorNet(ARCH), "base", backbone_weights="w.pt") == "scratch"


def test_detector_init_from_a_path_checks_the_architecture(tmp_path):
    torch.manual_seed(2)
    src = DetectorNet(ARCH)
    save_checkpoint(tmp_path / "d.pt", src)
    net = DetectorNet(ARCH)
    assert initialize_detector(net, str(tmp_path / "d.pt")) == str(tmp_path / "d.pt")
    torch.testing.assert_close(net.state_dict(), src.state_dict())
    wide = DetectorNet(DetectorConfig(input_size=64, width=0.5, neck_channels=8))
    with pytest.raises(DetectorInitError, match=r"width 0.25 \(this config: 0.5\)"):
        initialize_detector(wide, str(tmp_path / "d.pt"))


def test_fit_starts_from_the_base_and_stops_resumably(shipped, tmp_path):
    views = ViewImages([np.full((48, 64, 3), 100, np.uint8)] * 2, np.array([[4.0, 4, 30, 30]] * 2))
    cfg = DetectorTrainConfig(
        input_size=64, width=0.25, neck_channels=8, steps=4, batch_size=1, lr=1e-9,
        warmup_steps=1, checkpoint_every=10, log_every=1,
    )  # fmt: skip
    net, losses = fit(views, cfg, "cpu", out_dir=tmp_path, progress=False, stop_after=2)
    assert len(losses) == 2
    for k, v in net.state_dict().items():
        if v.is_floating_point() and "running" not in k:
            torch.testing.assert_close(v, shipped[k], atol=1e-5, rtol=0, msg=k)
    _, more = fit(views, cfg, "cpu", out_dir=tmp_path, resume=True, progress=False)
    assert len(more) == 2
