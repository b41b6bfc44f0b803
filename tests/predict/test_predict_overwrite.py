"""An existing output of ``merge``, ``render`` and ``export`` is never replaced without
``--overwrite``; ``render`` removes the temporary files a killed render of the same output
left, and refuses an output that another run holds."""

from __future__ import annotations

import os

import pytest
from click.testing import CliRunner
from predict_helpers import BlobEstimator, make_session

from freipose.cli.main import cli
from freipose.io.session import discover_sessions
from freipose.predict.run import predict_session


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """(session folder, complete poses file, folder with the two shards of a run)."""
    root = tmp_path_factory.mktemp("overwrite")
    folder = root / "rec"
    make_session(folder, 24)
    (s,) = discover_sessions([folder])
    poses = predict_session(s, BlobEstimator(), root / "poses", batch_size=4, progress=False)
    for i in range(2):
        predict_session(s, BlobEstimator(), root / "shards", batch_size=4, chunk_frames=8,
                        shard=(i, 2), progress=False)  # fmt: skip
    return folder, poses.path, root / "shards"


def _cli(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def test_merge_keeps_a_finished_output(run, tmp_path):
    _, _, shards = run
    res = _cli("merge", shards, "-o", tmp_path)
    assert res.exit_code == 0, res.output
    merged = tmp_path / "rec.poses.h5"
    before = merged.stat().st_mtime_ns
    res = _cli("merge", shards, "-o", tmp_path, "--remove-shards")
    assert res.exit_code != 0
    assert f"{merged} exists; pass --overwrite to replace it" in res.output
    assert merged.stat().st_mtime_ns == before
    assert len(list(shards.glob("*.shard-*.poses.h5"))) == 2  # nothing removed
    res = _cli("merge", shards, "-o", tmp_path, "--overwrite")
    assert res.exit_code == 0, res.output
    assert not list(tmp_path.glob("*.lock"))


def test_export_keeps_an_existing_export(run, tmp_path):
    _, poses, _ = run
    out = tmp_path / "p.csv"
    assert _cli("export", poses, "-o", out).exit_code == 0
    out.write_text("mine")
    res = _cli("export", poses, "-o", out)
    assert res.exit_code != 0 and f"{out} exists; pass --overwrite to replace it" in res.output
    assert out.read_text() == "mine"
    assert _cli("export", poses, "-o", out, "--overwrite").exit_code == 0
    assert out.read_text().startswith("frame,time_s,")


def test_render_keeps_an_existing_video_and_removes_leftovers(run, tmp_path):
    folder, poses, _ = run
    out = tmp_path / "o.mkv"
    args = ("render", folder, poses, "-o", out, "--frames", "0:3", "--tile-width", "64")
    assert _cli(*args).exit_code == 0
    before = out.read_bytes()
    res = _cli(*args)
    assert res.exit_code != 0 and f"{out} exists; pass --overwrite to replace it" in res.output
    assert out.read_bytes() == before
    # leftovers of killed renders of o.mkv go; other files stay
    left = [tmp_path / ".o.partial.mkv", tmp_path / ".o.ab12cd_9.partial.mkv"]
    kept = [tmp_path / ".other.partial.mkv", tmp_path / ".o.x.partial.mp4", tmp_path / "o.txt"]
    for p in left + kept:
        p.write_bytes(b"x")
    res = _cli(*args, "--overwrite")
    assert res.exit_code == 0, res.output
    assert not any(p.exists() for p in left) and all(p.exists() for p in kept)


def test_render_refuses_an_output_that_another_run_writes(run, tmp_path, lock_holders):
    folder, poses, _ = run
    out = tmp_path / "o.mkv"
    leftover = tmp_path / ".o.partial.mkv"
    leftover.write_bytes(b"being written")
    holder = lock_holders.hold(out)
    try:
        res = _cli("render", folder, poses, "-o", out, "--frames", "0:3", "--tile-width", "64")
        assert res.exit_code != 0
        assert f"pid {holder.pid}" in res.output
        assert f"is writing {out}; wait for it or pass another -o" in res.output
        assert leftover.read_bytes() == b"being written" and not out.exists()
    finally:
        lock_holders.release(holder)
    assert not os.path.exists(f"{out}.lock")
