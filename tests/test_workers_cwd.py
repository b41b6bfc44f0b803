"""Worker processes import the installed freipose whatever the working folder holds."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import pytest

import freipose
from freipose.errors import FreiPoseError
from freipose.workers import WorkerError, run_jobs, worker_errors

_SCRIPT = textwrap.dedent(
    """
    import json
    import sys

    from freipose.workers import process_pool, run_jobs


    def where(_):
        import freipose

        return str(freipose.__file__)


    if __name__ == "__main__":
        if sys.argv[1] == "forkserver":
            with process_pool(2, preload=["freipose.workers", "freipose.io.video"]) as ex:
                found = [ex.submit(where, i).result() for i in range(2)]
        else:
            found = run_jobs(where, [0, 1, 2], 2, "test", False, start_method=sys.argv[1])
        print(json.dumps(found))
    """
)


def _shadow(tmp_path: Path, init: str | None) -> Path:
    """A working folder holding a folder ``freipose`` (with ``__init__.py`` = ``init``)."""
    cwd = tmp_path / "work"
    (cwd / "freipose").mkdir(parents=True)
    if init is not None:
        (cwd / "freipose" / "__init__.py").write_text(init)
    return cwd


@pytest.mark.parametrize("start_method", ["forkserver", "spawn"])
@pytest.mark.parametrize(
    "init", [None, "raise ImportError('not the freipose package')"], ids=["empty", "raises"]
)
def test_workers_import_the_installed_package(tmp_path, start_method, init):
    cwd = _shadow(tmp_path, init)
    script = tmp_path / "scripts" / "job.py"  # a script elsewhere, like the console script
    script.parent.mkdir()
    script.write_text(_SCRIPT)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONSAFEPATH", "PYTHONPATH")}
    env["OMP_NUM_THREADS"] = "1"
    r = subprocess.run(
        [sys.executable, str(script), start_method],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert "Traceback" not in r.stderr, r.stderr[-3000:]
    found = json.loads(r.stdout.strip().splitlines()[-1])
    assert found == [freipose.__file__] * len(found)


def test_broken_pool_becomes_one_line_worker_error():
    with pytest.raises(WorkerError) as e, worker_errors():
        raise BrokenProcessPool("A process in the process pool was terminated abruptly")
    assert isinstance(e.value, FreiPoseError)
    msg = str(e.value)
    assert msg.startswith("a worker process died: ") and "\n" not in msg


def _exit_on_one(job: int) -> int:
    """A job whose worker dies without an error on job 1."""
    if job == 1:
        os._exit(3)
    return job


def test_dead_worker_in_run_jobs_names_its_exit_status():
    with pytest.raises(WorkerError) as e:
        run_jobs(_exit_on_one, [0, 1, 2, 3], 2, "test", False)
    msg = str(e.value)
    assert msg.startswith("a worker process died: it exited with status 3") and "\n" not in msg
    assert "--workers 1" in msg
