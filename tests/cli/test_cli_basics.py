"""The ``freipose`` entry point: version, help, and an example in every command's help."""

from __future__ import annotations

import os
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from freipose import __version__
from freipose.cli.main import cli


def _all_commands() -> list[tuple[str, ...]]:
    """Every command path (``("calib", "show")``, ...), found by walking the groups."""
    out: list[tuple[str, ...]] = []

    def walk(group: click.Group, prefix: tuple[str, ...]) -> None:
        ctx = click.Context(group, info_name=prefix[-1] if prefix else "freipose")
        for name in group.list_commands(ctx):
            out.append(prefix + (name,))
            try:
                cmd = group.get_command(ctx, name)
            except Exception:  # noqa: BLE001 - the help test of this path reports the error
                continue
            if isinstance(cmd, click.Group):
                walk(cmd, prefix + (name,))

    walk(cli, ())
    return out


def test_version_and_help():
    r = CliRunner().invoke(cli, ["--version"])
    assert r.exit_code == 0 and __version__ in r.output
    r = CliRunner().invoke(cli, ["--help"])
    assert r.exit_code == 0 and "Usage:" in r.output and "calib" in r.output
    assert "millimetres" in r.output.lower()
    assert CliRunner().invoke(cli, ["-h"]).exit_code == 0


def test_the_calibration_file_commands_exist():
    paths = _all_commands()
    assert ("calib",) in paths and ("calib", "convert") in paths and ("calib", "show") in paths


@pytest.mark.parametrize("path", _all_commands(), ids=lambda p: " ".join(p))
def test_every_command_has_help_with_an_example(path):
    r = CliRunner().invoke(cli, [*path, "--help"])
    assert r.exit_code == 0, f"{r.output}\n{r.exception!r}"
    assert "Example" in r.output, f"'freipose {' '.join(path)} --help' shows no Example section"
    summary = r.output.split("\n\n")[1].strip() if "\n\n" in r.output else ""
    assert summary, f"'freipose {' '.join(path)}' has no one-line summary"


def test_unknown_command_is_a_usage_error():
    r = CliRunner().invoke(cli, ["no-such-command"])
    assert r.exit_code == 2 and "No such command" in r.output


def test_user_errors_shows_freipose_errors_and_lets_bugs_through() -> None:
    import click
    import pytest

    from freipose.cli._common import user_errors
    from freipose.errors import FreiPoseError, InputFileError

    for err in (FreiPoseError("bad value; pass --x"), InputFileError("no such file: a.toml")):
        with pytest.raises(click.ClickException, match=str(err)), user_errors():
            raise err
    for bug in (ValueError("shape mismatch"), KeyError("k"), FileNotFoundError("x")):
        with pytest.raises(type(bug)), user_errors():
            raise bug


def test_library_warnings_stay_off_the_terminal_unless_verbose(tmp_path) -> None:
    """FFmpeg's own lines about a broken video show with -v only; FreiPose's error always."""
    import subprocess
    import sys

    import cv2
    import numpy as np

    good = tmp_path / "good.mp4"
    w = cv2.VideoWriter(str(good), cv2.VideoWriter_fourcc(*"mp4v"), 25, (64, 48))
    for i in range(30):
        w.write(np.full((48, 64, 3), 5 * i, np.uint8))
    w.release()
    data = good.read_bytes()
    for cam in ("cam0", "cam1"):
        (tmp_path / f"{cam}.mp4").write_bytes(data[: len(data) // 2])  # no moov atom
    board = Path(__file__).resolve().parents[2] / "examples" / "board.toml"
    args = [str(tmp_path / "cam0.mp4"), str(tmp_path / "cam1.mp4"), "--board", str(board),
            "-o", str(tmp_path / "c.toml")]  # fmt: skip
    env = {k: v for k, v in os.environ.items() if not k.startswith("OPENCV_")}

    def run(*pre: str) -> subprocess.CompletedProcess:
        code = "from freipose.cli.main import main; main()"
        return subprocess.run([sys.executable, "-c", code, *pre, "calib", *args],
                              capture_output=True, text=True, env=env, cwd=tmp_path)  # fmt: skip

    quiet, verbose = run(), run("-v")
    assert quiet.returncode != 0 and "cannot open this file as a video" in quiet.stderr
    assert "moov atom" not in quiet.stderr
    assert "moov atom" in verbose.stderr
