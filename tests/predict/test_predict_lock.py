"""Two runs never write into one poses file: while a run holds the output's lock, a second
``freipose predict`` on the same output says who holds it and leaves its ``.partial`` file
untouched."""

from __future__ import annotations

import pytest
import torch
from click.testing import CliRunner
from predict_helpers import TOY_KEYPOINTS, BlobEstimator, toy_rig, toy_session, toy_training_samples

from freipose.cli.main import cli
from freipose.io.lock import OutputLockedError
from freipose.io.session import discover_sessions
from freipose.predict.run import predict_session
from freipose.skeleton import Skeleton

T = 16


class _Kill(Exception):
    pass


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """(model.pt of a barely trained network, the toy session, the output folder holding
    the .partial file of a killed first run)."""
    from freipose.nn.config import config_from_dict
    from freipose.nn.train import train_pose

    root = tmp_path_factory.mktemp("lock")
    rig = toy_rig()
    cfg = config_from_dict(
        {
            "model": {"preset": "tiny", "cube_size": 300.0},
            "schedule": {"steps": 2, "checkpoint_every": 2, "eval_every": 2},
            "augment": {"enabled": False},
        }
    )
    torch.manual_seed(0)
    model = train_pose(cfg, root / "run", toy_training_samples(2, rig),
                       Skeleton("toy", TOY_KEYPOINTS), progress=False)  # fmt: skip
    toy_session(root / "toy", rig, T)
    (s,) = discover_sessions([root / "toy"])

    def kill(rows: int) -> None:
        if rows >= 8:
            raise _Kill

    with pytest.raises(_Kill):
        predict_session(s, BlobEstimator(), root / "out", batch_size=4, chunk_frames=4,
                        on_batch=kill, progress=False)  # fmt: skip
    assert (root / "out" / "toy.poses.h5.partial").is_file()
    return model, root / "toy", root / "out"


def test_second_predict_run_is_refused_and_touches_nothing(setup, lock_holders):
    model, session, out = setup
    final = out / "toy.poses.h5"
    partial = out / "toy.poses.h5.partial"
    before = (partial.read_bytes(), partial.stat().st_mtime_ns)
    holder = lock_holders.hold(final, "poses file")
    try:
        args = ["predict", str(session), "--model", str(model), "--method", "bgsub",
                "--device", "cpu", "-o", str(out)]  # fmt: skip
        res = CliRunner().invoke(cli, args)
        assert res.exit_code != 0
        msg = " ".join(res.output.split())
        assert f"Error: another run ({holder.pid}" not in msg  # host first, then pid
        assert f", pid {holder.pid}, started " in msg
        assert f"is writing {final}; wait for it or pass another -o" in msg
        assert (partial.read_bytes(), partial.stat().st_mtime_ns) == before
        assert not final.exists()
        (s,) = discover_sessions([session])
        with pytest.raises(OutputLockedError, match="another run"):
            predict_session(s, BlobEstimator(), out, batch_size=4, chunk_frames=4, progress=False)
        assert (partial.read_bytes(), partial.stat().st_mtime_ns) == before
    finally:
        lock_holders.release(holder)
    assert not (out / "toy.poses.h5.lock").exists()
