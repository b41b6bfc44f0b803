"""A unit whose output disk is full, on a real SLURM scheduler, then freed and resumed.

The output folder is a real 16 MB tmpfs. Two toy sessions of 2 units (24 and 16
frames) run one unit at a time (``array_parallelism = 1``); when 3 units are done the disk
is filled up to less than the last unit's part can take. That unit fails, is retried, and
fails again; the run ends with a report naming the unit, the full disk and its path, the
session that had no room to be joined (its parts are kept), and the command that finishes
it. After the space is freed, ``freipose jobs OUTDIR --resume`` runs only that unit, and
every session's joined file equals the direct run's bit for bit (each frame exactly once).

Mounting a tmpfs needs root (CAP_SYS_ADMIN); the test skips with the reason elsewhere.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import SESSIONS, cluster_file, predict_args, slurm_reason
from predict_helpers import h5_equal

from freipose.cluster.driver import read_journal

pytestmark = pytest.mark.slurm

STUDY = SESSIONS[:2]
PER_SESSION = 2  # units of 24 and 16 frames
UNITS = 2 * PER_SESSION
HEADROOM = 40 * 1024  # bytes left free: less than one unit's part needs (over 64 KiB)


def _mount(folder: Path, options: str) -> None:
    subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)],
                   check=True, capture_output=True, text=True)  # fmt: skip


def _umount(folder: Path) -> None:
    subprocess.run(["umount", str(folder)], check=False, capture_output=True)


@pytest.fixture
def out(tmp_path: Path) -> Iterator[Path]:
    """The output folder: a 16 MB tmpfs (skip where SLURM is down or mounting is refused)."""
    reason = slurm_reason()
    if reason is not None:
        pytest.skip(reason)
    folder = tmp_path / "poses"
    folder.mkdir()
    try:
        _mount(folder, "size=16m")
    except (OSError, subprocess.CalledProcessError) as exc:
        why = getattr(exc, "stderr", "") or exc
        pytest.skip(f"cannot mount a tmpfs here (needs root with CAP_SYS_ADMIN): {why}")
    try:
        yield folder
    finally:
        for job in {e["job_id"].split("_")[0] for e in read_journal(folder) if "job_id" in e}:
            subprocess.run(["scancel", job], check=False, capture_output=True)
        _umount(folder)


def _fill(folder: Path, leave: int) -> Path:
    """Take the free space of ``folder``'s disk but ``leave`` bytes; returns the filler."""
    import shutil

    filler = folder / "filler"
    with open(filler, "ab", buffering=0) as f:
        while (free := shutil.disk_usage(folder).free) > leave:
            f.write(bytes(min(1 << 20, max(4096, free - leave))))
    return filler


def _done_units(folder: Path) -> int:
    """Units whose own record says they finished."""
    n = 0
    for f in (folder / ".jobs" / "units").glob("*.json"):
        try:
            n += json.loads(f.read_text()).get("state") == "done"
        except (OSError, json.JSONDecodeError):
            continue
    return n


def _freipose(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "freipose.cli.main", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=False)


@pytest.mark.slow
def test_full_output_disk_for_one_unit_is_reported_then_resumed(toy_study, out, tmp_path):
    cfg = cluster_file(tmp_path, executor="slurm", chunk_frames=24, array_parallelism=1,
                       poll_s=0.5, max_retries=1, cpus=1, mem_gb=1, time_min=10)  # fmt: skip
    study = {**toy_study, "sessions": toy_study["sessions"][: len(STUDY)]}
    cmd = [sys.executable, "-m", "freipose.cli.main",
           *predict_args(study, out, "--cluster", str(cfg))]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    filler = None
    try:
        deadline = time.monotonic() + 400
        while proc.poll() is None and time.monotonic() < deadline:
            if _done_units(out) == UNITS - 1:
                filler = _fill(out, HEADROOM)
                break
            time.sleep(0.1)
        output, _ = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert filler is not None, f"the run ended before {UNITS - 1} units were done:\n{output}"
    assert proc.returncode == 1, output
    assert "Traceback" not in output, output
    (failed,) = {e["unit"] for e in read_journal(out) if e["event"] == "failed"}
    session, index = failed.split(".")[0], int(failed.split(".")[1].split("-")[0])
    part = out / f"{session}.shard-{index}-of-{PER_SESSION}.poses.h5"
    assert f"1 of {UNITS} units failed" in output, output
    assert f"{failed}: " in output and "after 2 jobs" in output, output
    assert f"cannot write {part}" in output and "free space there" in output, output
    assert f"freipose jobs {out} --resume" in output, output
    assert not (out / f"{session}.poses.h5").exists(), "a session joined without a unit"
    for s in set(STUDY) - {session}:  # complete, but no room to join it: said, parts kept
        assert f"{s}: its units are done, its parts kept, but it was not joined" in output
        assert len(list(out.glob(f"{s}.shard-*-of-{PER_SESSION}.poses.h5"))) == PER_SESSION
    status = _freipose("jobs", str(out))
    shown = status.stdout + status.stderr
    assert f"{session}: {PER_SESSION - 1} done, 1 failed" in status.stdout, shown
    assert f"finish with: freipose jobs {out} --resume" in status.stdout
    for s in set(STUDY) - {session}:
        assert f"{s}: {PER_SESSION} done, not joined" in status.stdout, shown

    filler.unlink()  # the space is given back: the resumed run submits only that unit
    before = len(read_journal(out))
    resumed = _freipose("jobs", str(out), "--resume")
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    events = read_journal(out)
    again = [e["unit"] for e in events[before:] if e["event"] == "submitted"]
    assert again == [failed], events[before:]
    for s in STUDY:  # each frame exactly once, equal to the direct run
        assert h5_equal(toy_study["direct"] / f"{s}.poses.h5", out / f"{s}.poses.h5") == []
    assert not list(out.glob("*.shard-*")) and not list(out.glob("*.partial"))
    assert all(f"{s}: {PER_SESSION} done" in resumed.stdout for s in STUDY), resumed.stdout
