"""detect and smooth through a real SLURM scheduler (the single-node SLURM of ``.ci/run``):
the units' outputs equal a direct run's bit for bit, and ``freipose jobs`` lists the jobs."""

from __future__ import annotations

import subprocess
import sys

import pytest
from conftest import cluster_file, slurm_reason
from predict_helpers import h5_equal
from test_stages import DETECT, _run, inputs  # noqa: F401 - the fixture

pytestmark = pytest.mark.slurm


def _freipose(*args: object) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "freipose.cli.main", *map(str, args)]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=600, check=False)


@pytest.mark.slow
def test_detect_and_smooth_units_on_slurm(inputs, tmp_path):  # noqa: F811 - the fixture
    reason = slurm_reason()
    if reason is not None:
        pytest.skip(reason)
    cfg = cluster_file(tmp_path, executor="slurm", chunk_frames=8, array_parallelism=3,
                       poll_s=0.5, max_retries=1, cpus=1, mem_gb=1, time_min=10)  # fmt: skip
    s0 = inputs["sessions"][0]
    _run("detect", s0, *DETECT, "-o", tmp_path / "direct.h5")
    out = tmp_path / "boxes" / "s0.boxes.h5"
    res = _freipose("detect", s0, *DETECT, "-o", out, "--cluster", cfg)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "3 units done (3 jobs submitted in this run)" in res.stdout
    assert h5_equal(tmp_path / "direct.h5", out) == []
    status = _freipose("jobs", out, "--all")
    assert "on the slurm executor" in status.stdout and "s0: 3 done" in status.stdout
    assert "s0.2-of-3: done, job " in status.stdout, status.stdout

    poses = inputs["poses"]
    _run("smooth", *poses, "-o", tmp_path / "direct")
    res = _freipose("smooth", *poses, "-o", tmp_path / "smoothed", "--cluster", cfg)
    assert res.returncode == 0, res.stdout + res.stderr
    for p in poses:
        assert h5_equal(tmp_path / "direct" / p.name, tmp_path / "smoothed" / p.name) == []
