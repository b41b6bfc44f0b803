"""--threads of train, predict and demo reaches torch.get_num_threads()."""

from __future__ import annotations

import pytest
import torch
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.errors import FreiPoseError


class _Stop(FreiPoseError):
    """Raised by the patched library call once it has seen the thread count."""


@pytest.fixture
def seen(monkeypatch):
    """The torch thread counts the patched library calls saw; torch's setting restored."""
    before = torch.get_num_threads()
    counts: list[int] = []

    def record(*args, **kwargs):
        counts.append(torch.get_num_threads())
        raise _Stop("stopped after the thread count was set")

    monkeypatch.setattr("freipose.nn.train.train_from_config", record)
    monkeypatch.setattr("freipose.io.session.discover_sessions", record)
    monkeypatch.setattr("freipose.io.checkpoints.check_checkpoints", lambda *a: None)
    monkeypatch.setattr("freipose.demo.runner.run_demo", record)
    yield counts
    torch.set_num_threads(before)


def test_threads_option_reaches_torch(seen, tmp_path, monkeypatch):
    cfg = tmp_path / "cfg.toml"
    cfg.write_text("[model]\npreset = 'tiny'\n")
    model = tmp_path / "model.pt"
    model.write_bytes(b"x")
    runs = [
        ["train", str(cfg), "--threads", "1"],
        ["train", str(cfg), "--threads", "2"],
        ["predict", str(tmp_path), "--model", str(model), "-o", str(tmp_path / "p"),
         "--method", "bgsub", "--threads", "1"],
        ["demo", str(tmp_path / "d"), "--threads", "2"],
        ["demo", str(tmp_path / "d"), "--threads", "1"],
    ]  # fmt: skip
    for args in runs:
        r = CliRunner().invoke(cli, args)
        assert "stopped after the thread count was set" in r.output, r.output
    assert seen == [1, 2, 1, 2, 1]
    # under torchrun, the free cores are shared by the processes on this machine
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr("freipose.workers.cpu_cores", lambda: 8)
    monkeypatch.setattr("freipose.workers.other_load", lambda: 0.0)
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "4")
    CliRunner().invoke(cli, ["train", str(cfg)])
    assert seen[-1] == 2
    r = CliRunner().invoke(cli, ["train", str(cfg), "--threads", "0"])
    assert r.exit_code != 0 and "--threads must be at least 1" in r.output
