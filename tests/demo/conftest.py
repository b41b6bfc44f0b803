"""The tiny demo run that the demo tests share (one run per test session)."""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from freipose.cli.main import cli


@pytest.fixture(scope="session")
def tiny_demo(tmp_path_factory):
    """``freipose demo OUT --preset tiny``: the folder and the printed output."""
    out = tmp_path_factory.mktemp("demo") / "demo_out"
    res = CliRunner().invoke(cli, ["demo", str(out), "--preset", "tiny"])
    assert res.exit_code == 0, res.output + repr(res.exception)
    return out, res.output
