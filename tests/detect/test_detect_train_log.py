"""The detector trainer's ``log.csv``: one row per ``log_every`` steps, kept up to a resume."""

import numpy as np
import pytest
import torch

import freipose.detect.train as train_module
from freipose.detect.train import DetectorTrainConfig, ViewImages, fit
from freipose.detect.train_log import LOG, LOG_COLUMNS, read_log


def _views(n: int = 8) -> ViewImages:
    rng = np.random.default_rng(3)
    imgs = [rng.integers(0, 100, (48, 64, 3)).astype(np.uint8) for _ in range(n)]
    boxes = np.array([[10.5, 8.5, 30.5, 20.5]] * n)
    return ViewImages(imgs, boxes)


CFG = DetectorTrainConfig(
    input_size=64, width=0.25, neck_channels=8, steps=6, batch_size=2, warmup_steps=1,
    checkpoint_every=3, log_every=2,
)  # fmt: skip


def test_log_rows_hold_the_window_mean_loss(tmp_path):
    torch.set_num_threads(1)
    _, losses = fit(_views(), CFG, "cpu", out_dir=tmp_path, progress=False)
    rows = read_log(tmp_path / LOG)
    assert (tmp_path / LOG).read_text().splitlines()[0] == ",".join(LOG_COLUMNS)
    assert [int(r["step"]) for r in rows] == [2, 4, 6]
    for r, k in zip(rows, (0, 2, 4)):
        assert float(r["loss"]) == pytest.approx(np.mean(losses[k : k + 2]), rel=1e-5)
        assert all(r[c] != "" for c in LOG_COLUMNS)


def test_resume_keeps_the_rows_up_to_the_checkpoint(tmp_path, monkeypatch):
    torch.set_num_threads(1)
    calls = []
    real = train_module.detection_loss

    def interrupted(*args, **kwargs):
        calls.append(1)
        if len(calls) == 5:  # after the checkpoint at step 3 and the row of step 4
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(train_module, "detection_loss", interrupted)
    with pytest.raises(KeyboardInterrupt):
        fit(_views(), CFG, "cpu", out_dir=tmp_path, progress=False)
    assert [r["step"] for r in read_log(tmp_path / LOG)] == ["2", "4"]
    monkeypatch.setattr(train_module, "detection_loss", real)
    fit(_views(), CFG, "cpu", out_dir=tmp_path, resume=True, progress=False)
    assert [r["step"] for r in read_log(tmp_path / LOG)] == ["2", "4", "6"]
    assert read_log(tmp_path / LOG, upto=4)[-1]["step"] == "4"
