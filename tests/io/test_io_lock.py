"""freipose.io.lock: the exclusive output lock."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys

import pytest

from freipose.io.lock import OutputLockedError, lock_path, output_lock


def _write_lock(out, host, pid):
    lock_path(out).write_text(
        json.dumps(
            {
                "host": host,
                "pid": pid,
                "started": "2026-01-01T00:00:00+00:00",
                "command": "freipose predict",
            }
        )
    )


def test_lock_taken_and_released(tmp_path):
    out = tmp_path / "poses" / "x.poses.h5"
    with output_lock(out) as lock:
        assert lock == tmp_path / "poses" / "x.poses.h5.lock" == lock_path(out)
        d = json.loads(lock.read_text())
        assert d["host"] == socket.gethostname() and d["pid"] == os.getpid()
        assert d["started"] and d["command"]
    assert not lock.exists()
    with output_lock(out):  # free again
        pass


def test_second_run_is_refused_and_leaves_the_lock(tmp_path, lock_holders):
    out = tmp_path / "x.poses.h5"
    holder = lock_holders.hold(out)
    try:
        before = lock_path(out).read_bytes()
        with pytest.raises(OutputLockedError) as e, output_lock(out):
            pass
        msg = str(e.value)
        assert f"({socket.gethostname()}, pid {holder.pid}, started " in msg
        assert f"is writing {out}; wait for it or pass another -o" in msg
        assert "delete" not in msg  # this host: the pid was checked
        assert lock_path(out).read_bytes() == before
    finally:
        lock_holders.release(holder)
    assert holder.returncode == 0
    assert not lock_path(out).exists()


def test_stale_lock_of_a_finished_process_is_taken_over(tmp_path, caplog):
    out = tmp_path / "x.poses.h5"
    done = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"],
        capture_output=True,
        text=True,
        check=True,
    )
    dead = int(done.stdout)
    _write_lock(out, socket.gethostname(), dead)
    with caplog.at_level("WARNING", logger="freipose.io.lock"), output_lock(out) as lock:
        assert json.loads(lock.read_text())["pid"] == os.getpid()
    assert f"pid {dead}" in caplog.text and "stale" in caplog.text
    assert not lock.exists()


def test_lock_of_another_host_is_refused_with_the_delete_hint(tmp_path):
    out = tmp_path / "x.poses.h5"
    _write_lock(out, "other-host.example", 4242)
    with pytest.raises(OutputLockedError) as e, output_lock(out):
        pass
    assert str(e.value) == (
        f"another run (other-host.example, pid 4242, started 2026-01-01T00:00:00+00:00) is "
        f"writing {out}; wait for it or pass another -o; if that run is gone, delete "
        f"{lock_path(out)}"
    )
    assert json.loads(lock_path(out).read_text())["host"] == "other-host.example"


def test_unreadable_lock_is_stale_only_when_old(tmp_path):
    out = tmp_path / "x.poses.h5"
    lock_path(out).write_text("{not json")
    with pytest.raises(OutputLockedError, match="cannot be read"), output_lock(out):
        pass
    old = lock_path(out).stat().st_mtime - 120
    os.utime(lock_path(out), (old, old))
    with output_lock(out) as lock:
        assert json.loads(lock.read_text())["pid"] == os.getpid()


def test_lock_removed_when_the_block_raises(tmp_path):
    out = tmp_path / "x.poses.h5"
    with pytest.raises(RuntimeError, match="boom"), output_lock(out):
        assert lock_path(out).exists()
        raise RuntimeError("boom")
    assert not lock_path(out).exists()


def test_lock_replaced_meanwhile_is_left_alone(tmp_path):
    out = tmp_path / "x.poses.h5"
    with output_lock(out) as lock:
        _write_lock(out, "other-host.example", 1)
    assert json.loads(lock.read_text())["host"] == "other-host.example"
