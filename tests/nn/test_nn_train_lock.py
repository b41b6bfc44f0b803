"""Two trainings into one run folder: the second (new or --resume) is refused by the run
folder's lock, names the run that holds it and the real option, and touches nothing."""

from __future__ import annotations

import socket

import pytest
from click.testing import CliRunner
from nn_toydata import toy_samples, write_toy_labels

from freipose.cli.main import cli


def _snapshot(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


@pytest.mark.parametrize("stage", ["pose", "detector"])
def test_second_training_into_a_locked_run_folder_is_refused(tmp_path, lock_holders, stage):
    write_toy_labels(tmp_path / "train", toy_samples(2))
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(
        '[data]\nlabels = "train/labels.h5"\n[model]\npreset = "tiny"\n[schedule]\nsteps = 2\n'
        "[detector]\ninput_size = 64\nwidth = 0.25\nneck_channels = 8\nsteps = 2\n"
        "batch_size = 1\n"
    )
    run = tmp_path / "run"
    run.mkdir()
    checkpoint = run / ("checkpoint.pt" if stage == "pose" else "detector_last.pt")
    checkpoint.write_bytes(b"the other run's checkpoint")
    (run / "log.csv").write_text("step,lr,loss\n1,0.001,0.5\n")
    (run / "config.toml").write_text("[model]\n")
    pid = lock_holders.hold(checkpoint).pid
    before = _snapshot(run)
    for resume in ([], ["--resume"]):
        args = ["train", str(cfg), "--stage", stage, "--out", str(run), *resume]
        res = CliRunner().invoke(cli, args)
        assert res.exit_code != 0, res.output
        assert f"another run ({socket.gethostname()}, pid {pid}, started " in res.output
        assert f"is writing {checkpoint}; wait for it or pass another --out" in res.output
        assert _snapshot(run) == before
