"""Fixtures of the cluster tests: a tiny network, three toy sessions and their direct run;
a tiny training run of two gloo processes that the training tests continue or repeat."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "predict"))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "nn"))

from nn_toydata import toy_samples, write_toy_labels  # noqa: E402
from predict_helpers import TOY_KEYPOINTS, toy_rig, toy_session, toy_training_samples  # noqa: E402

from freipose.cli.main import cli  # noqa: E402
from freipose.nn.checkpoint import read_checkpoint  # noqa: E402

FRAMES = 40  # 5 units of 8 frames per session
SESSIONS = ("s0", "s1", "s2")
PREDICT = ["--method", "bgsub", "--batch", "4", "--device", "cpu", "--threads", "1"]
#: steps and checkpoint interval of the shared training run of two gloo processes
STEPS, EVERY = 30, 4
#: that run's job: the local executor, 2 processes of 1 thread (as a SLURM task of 1 CPU)
LOCAL_JOB = ["--executor", "local", "--tasks-per-node", "2", "--threads", "1"]


@pytest.fixture(scope="session")
def toy_study(tmp_path_factory) -> dict:
    """model.pt (a tiny network after 2 steps), 3 sessions of 40 frames, and a direct run."""
    from freipose.nn.config import config_from_dict
    from freipose.nn.train import train_pose
    from freipose.skeleton import Skeleton

    root = tmp_path_factory.mktemp("study")
    rig = toy_rig()
    cfg = config_from_dict(
        {
            "model": {"preset": "tiny", "cube_size": 300.0, "init": "scratch"},
            "schedule": {"steps": 2, "lr": 3e-3, "checkpoint_every": 2, "eval_every": 2},
            "augment": {"enabled": False},
        }
    )
    torch.manual_seed(0)
    model = train_pose(
        cfg, root / "run", toy_training_samples(4, rig), Skeleton("toy", TOY_KEYPOINTS),
        progress=False,
    )  # fmt: skip
    sessions = [root / s for s in SESSIONS]
    for i, s in enumerate(sessions):
        toy_session(s, rig, FRAMES, seed=i + 1)
    direct = root / "direct"
    res = CliRunner().invoke(
        cli, ["predict", *map(str, sessions), "--model", str(model), *PREDICT, "-o", str(direct)]
    )
    assert res.exit_code == 0, res.output
    return {"root": root, "model": model, "sessions": sessions, "direct": direct}


def predict_args(study: dict, out: Path, *extra: str) -> list[str]:
    """``freipose predict`` of the toy study into ``out`` with ``extra`` options."""
    return ["predict", *map(str, study["sessions"]), "--model", str(study["model"]), *PREDICT,
            "-o", str(out), *extra]  # fmt: skip


def cluster_file(folder: Path, **values: object) -> Path:
    """A cluster TOML file with ``values`` in its ``[cluster]`` table."""
    import tomli_w

    path = folder / "cluster.toml"
    path.write_text(tomli_w.dumps({"cluster": values}), encoding="utf-8")
    return path


def slurm_reason() -> str | None:
    """Why the SLURM tests cannot run here (None: a SLURM node is up and submitit is there)."""
    try:
        import submitit  # noqa: F401
    except ImportError:
        return "submitit is not installed (pip install 'freipose[cluster]')"
    if shutil.which("sbatch") is None or shutil.which("sinfo") is None:
        return "SLURM is not installed (.ci/run installs and starts a single-node SLURM)"
    try:
        out = subprocess.run(["sinfo", "-h", "-o", "%T"], capture_output=True, text=True,
                             timeout=20, check=False)  # fmt: skip
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"sinfo failed: {exc}"
    if out.returncode != 0 or not {"idle", "mixed", "allocated", "mix", "alloc"} & set(
        out.stdout.split()
    ):
        return f"no SLURM node is up (sinfo: {(out.stdout + out.stderr).strip()!r})"
    return None


def squeue_state(job_id: str) -> str:
    """The job's state in ``squeue`` (``PENDING``, ``RUNNING``, ...); empty once it left."""
    out = subprocess.run(["squeue", "-h", "-j", job_id, "-o", "%T"], capture_output=True,
                         text=True, check=False).stdout.split()  # fmt: skip
    return out[0] if out else ""


def train_config(folder: Path, steps: int, checkpoint_every: int) -> Path:
    """A tiny training config on 4 toy samples, global batch 4 (2 per process)."""
    write_toy_labels(folder / "data", toy_samples(4))
    path = folder / "cfg.toml"
    path.write_text(
        '[data]\nlabels = "data/labels.h5"\n'
        '[model]\npreset = "tiny"\ncube_size = 300.0\ninit = "scratch"\n'
        f"[schedule]\nsteps = {steps}\ncheckpoint_every = {checkpoint_every}\nbatch_size = 4\n"
        "[augment]\nenabled = false\n"
    )
    return path


def same_weights(a: Path, b: Path) -> bool:
    """Whether two checkpoints hold the same weights, bit for bit."""
    wa, wb = read_checkpoint(a)["model"], read_checkpoint(b)["model"]
    return wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)


def logged_steps(run: Path) -> list[int]:
    """The steps of the run's log.csv, in order."""
    return [int(r.split(",")[0]) for r in (run / "log.csv").read_text().split()[1:]]


@pytest.fixture(scope="session")
def gloo_run(tmp_path_factory) -> dict:
    """``freipose train`` of :func:`train_config` (STEPS, EVERY) as a local job of 2 gloo
    processes, uninterrupted: its ``config``, run folder ``run`` and printed ``output``.

    The training tests compare their interrupted and resumed runs with it, bit for bit.
    """
    root = tmp_path_factory.mktemp("gloo")
    cfg = train_config(root, steps=STEPS, checkpoint_every=EVERY)
    run = root / "whole"
    res = CliRunner().invoke(cli, ["-q", "train", str(cfg), "--out", str(run), *LOCAL_JOB])
    assert res.exit_code == 0, res.output
    return {"config": cfg, "run": run, "output": res.output}
