"""``freipose detect`` keeps an existing boxes file unless ``--overwrite`` and refuses an
output that another run is writing."""

from __future__ import annotations

from click.testing import CliRunner

from freipose.cli.main import cli


def test_detect_keeps_an_existing_output(session_dir, tmp_path):
    out = tmp_path / "boxes.h5"
    args = ["detect", str(session_dir), "--method", "bgsub", "--frames", "0:4", "-o", str(out)]
    assert CliRunner().invoke(cli, args).exit_code == 0
    before = out.read_bytes()
    res = CliRunner().invoke(cli, args)
    assert res.exit_code != 0 and f"{out} exists; pass --overwrite to replace it" in res.output
    assert out.read_bytes() == before
    leftover = tmp_path / ".boxes.abcd1234.partial.h5"  # of a killed write of boxes.h5
    leftover.write_bytes(b"x")
    res = CliRunner().invoke(cli, [*args, "--overwrite"])
    assert res.exit_code == 0, res.output
    assert not leftover.exists() and not (tmp_path / "boxes.h5.lock").exists()


def test_detect_refuses_an_output_that_another_run_writes(session_dir, tmp_path, lock_holders):
    out = tmp_path / "boxes.h5"
    holder = lock_holders.hold(out)
    try:
        args = ["detect", str(session_dir), "--method", "bgsub", "--frames", "0:4", "-o", str(out)]
        res = CliRunner().invoke(cli, args)
        assert res.exit_code != 0
        assert f"pid {holder.pid}" in res.output
        assert f"is writing {out}; wait for it or pass another -o" in res.output
        assert not out.exists()
    finally:
        lock_holders.release(holder)
