"""The README, the docs and every ``--help`` text describe the product, briefly and truly.

- README.md stays a product page: at most 200 lines, and its two commands (the demo; the
  tests) are the ones CI runs.
- No text a user reads tells the history of the work ("session 12 measured ...").
- Every local link of the README points to a file that exists.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import click
import pytest

from freipose.cli.main import cli

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"

#: "session 12", "sessions 14 and 16-19", "session-20": a numbered work session
#: (not an option such as --sessions N or --detector-sessions N)
HISTORY = re.compile(r"(?<!-)\bsessions?[ -]\d+", re.I)


def _history(text: str) -> list[str]:
    return [line.strip() for line in text.splitlines() if HISTORY.search(line)]


def _commands(group: click.Command, prefix: tuple[str, ...] = ()) -> Iterator[tuple[str, ...]]:
    """Every command path under ``group`` (the group itself included)."""
    yield prefix
    if isinstance(group, click.Group):
        ctx = click.Context(group)
        for name in group.list_commands(ctx):
            sub = group.get_command(ctx, name)
            if sub is not None:
                yield from _commands(sub, (*prefix, name))


def _help_text(path: tuple[str, ...]) -> str:
    from click.testing import CliRunner

    res = CliRunner().invoke(cli, [*path, "--help"], terminal_width=100)
    assert res.exit_code == 0, (path, res.output)
    return res.output


def test_history_detector_finds_what_it_should() -> None:
    assert _history("measured in session 12 on AVX2")
    assert _history("sessions 14 and 16-19")
    assert not _history("one folder per session\nsession/cam0.mp4\nsessions of 30 s")
    assert not _history("python benchmarks/train_base.py --sessions 96")
    assert not _history("python benchmarks/social.py --detector-sessions 6")
    assert _history("as in session-20")


def test_readme_is_a_short_product_page() -> None:
    text = README.read_text(encoding="utf-8")
    n = len(text.splitlines())
    assert n <= 200, f"README.md has {n} lines; keep it a product page of at most 200"
    assert not _history(text), _history(text)


@pytest.mark.parametrize("doc", sorted((ROOT / "docs").rglob("*.md")), ids=lambda p: p.name)
def test_docs_tell_no_history(doc: Path) -> None:
    assert not _history(doc.read_text(encoding="utf-8")), (doc, _history(doc.read_text()))


def test_no_help_text_tells_history() -> None:
    paths = list(_commands(cli))
    assert len(paths) > 20  # every command and subcommand, not just the group
    found = {" ".join(p) or "freipose": _history(_help_text(p)) for p in paths}
    assert not {k: v for k, v in found.items() if v}


def test_readme_commands_are_the_ones_ci_runs() -> None:
    text = README.read_text(encoding="utf-8")
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    test_cmd = re.search(r"^pip install torch==(\S+) && pip install -e \"\.\[([\w,]+)\]\" && "
                         r"(python -m pytest)$", text, re.M)  # fmt: skip
    assert test_cmd, "README lost its test command"
    torch_pin, extras, pytest_cmd = test_cmd.groups()
    assert f"torch=={torch_pin}" in ci
    assert re.search(rf"^{re.escape(pytest_cmd)}$", ci, re.M), "CI must run the README's command"
    # the default suite leaves out the tests marked slow; CI must still run them
    assert "-m 'not slow'" in (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    assert re.search(rf"^{re.escape(pytest_cmd)} -m slow$", ci, re.M), "CI must run the slow tests"
    assert "-m slow" in text, "the README must say how to run the slow tests"
    ci_extras = set(re.search(r'-e "\.\[([\w,]+)\]"', ci).group(1).split(","))
    assert set(extras.split(",")) <= ci_extras
    demo = re.search(r"^pip install torch==(\S+) && pip install -e \. && freipose demo", text, re.M)
    assert demo and demo.group(1) == torch_pin


def test_readme_links_exist() -> None:
    text = README.read_text(encoding="utf-8")
    links = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    local = [link for link in links if "://" not in link]
    assert local
    missing = [link for link in local if not (ROOT / link).exists()]
    assert not missing, f"README links to files that do not exist: {missing}"
