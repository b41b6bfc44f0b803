"""Every option and config key that an error message tells the user to pass exists.

The messages are collected from the source of ``freipose/``, ``cli/`` and
``calibration/``: the string parts (constants and f-string pieces) of every ``raise X(...)``
call and of every call of a class named ``...Error``/``...Exception`` (errors that are
built and returned, then raised elsewhere). In them:

* each ``--option`` and each short option (``-o``) must be an option of some ``freipose``
  command (the click command tree from :data:`freipose.cli.main.cli`);
* each config key written as ``section.key`` (``data.root``, ``schedule.lr``,
  ``detector.steps``) must be a key of that table of the training config;
* a Python keyword argument (``pass root=``) must come with the command-line option that
  does the same (``pass overwrite=True (--overwrite)``): the CLI user has no keyword
  arguments.
"""

from __future__ import annotations

import ast
import dataclasses
import re
from collections.abc import Iterator
from pathlib import Path

import click
import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ("freipose", "cli", "calibration")

LONG = re.compile(r"(?<![\w-])--[a-zA-Z][\w-]*")
SHORT = re.compile(r"(?<![\w-])-[a-zA-Z](?![\w-])")
KEY = re.compile(r"(?<![\w.])(data|model|schedule|augment|detector)\.([a-z_]\w*)")
KWARG = re.compile(r"\bpass (\w+)=")
#: ``section.name`` mentions that are file names, not config keys (``model.pt``)
FILE_SUFFIXES = {"pt", "h5", "toml", "csv", "json", "png", "mp4", "avi"}
#: text about other programs' options, removed before the options are collected
OTHER_PROGRAMS = (
    "ffmpeg -r",  # "re-encode the videos with a frame rate (e.g. ffmpeg -r 30 ...)"
)


@dataclasses.dataclass(frozen=True)
class Message:
    """The text of one error message (its parts joined by NUL) and where it is."""

    where: str
    text: str


def _callee(call: ast.Call) -> str:
    f = call.func
    return f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else ""


def _strings(node: ast.AST) -> Iterator[str]:
    for n in ast.walk(node):
        if isinstance(n, ast.Constant) and isinstance(n.value, str):
            yield n.value


def error_messages() -> list[Message]:
    """The string parts of every error built in the sources (see the module docstring)."""
    out = []
    seen: set[int] = set()
    for top in SOURCES:
        for path in sorted((ROOT / top).rglob("*.py")):
            tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
            for node in ast.walk(tree):
                calls = []
                if isinstance(node, ast.Raise) and isinstance(node.exc, ast.Call):
                    calls.append(node.exc)
                if isinstance(node, ast.Call) and re.search(r"(Error|Exception)$", _callee(node)):
                    calls.append(node)
                for call in calls:
                    if id(call) in seen:
                        continue
                    seen.add(id(call))
                    args = [*call.args, *(k.value for k in call.keywords)]
                    text = "\0".join(s for a in args for s in _strings(a))
                    where = f"{path.relative_to(ROOT)}:{call.lineno}"
                    out.append(Message(where, text))
    return out


def cli_options() -> set[str]:
    """Every option name (``--out``, ``-o``, ``--no-refine``) of every ``freipose`` command."""
    from freipose.cli.main import cli

    names: set[str] = set()

    def walk(cmd: click.Command, ctx: click.Context) -> None:
        for p in cmd.params:
            if isinstance(p, click.Option):
                names.update(p.opts)
                names.update(p.secondary_opts)
        if isinstance(cmd, click.Group):
            for name in cmd.list_commands(ctx):
                sub = cmd.get_command(ctx, name)
                if sub is not None:
                    walk(sub, click.Context(sub, parent=ctx, info_name=name))

    walk(cli, click.Context(cli, info_name="freipose"))
    return names


def config_keys() -> dict[str, set[str]]:
    """Table -> its keys, for the tables of the training config."""
    from freipose.detect.train import DetectorTrainConfig
    from freipose.nn.config import AugmentConfig, DataConfig, ModelConfig, ScheduleConfig

    def keys(cls: type) -> set[str]:
        return {f.name for f in dataclasses.fields(cls)}

    return {
        "data": keys(DataConfig),
        "model": keys(ModelConfig) | {"preset"},
        "schedule": keys(ScheduleConfig),
        "augment": keys(AugmentConfig),
        "detector": keys(DetectorTrainConfig),
    }


@pytest.fixture(scope="module")
def messages() -> list[Message]:
    found = error_messages()
    assert len(found) > 300  # the collector sees the messages
    return found


def _without_other_programs(text: str) -> str:
    for s in OTHER_PROGRAMS:
        text = text.replace(s, "")
    return text


def test_every_option_in_an_error_message_exists(messages):
    options = cli_options()
    assert {"--out", "--resume", "--root", "-o", "--detector"} <= options
    bad = [
        f"{m.where}: {opt}"
        for m in messages
        for opt in LONG.findall(_without_other_programs(m.text))
        + SHORT.findall(_without_other_programs(m.text))
        if opt not in options
    ]
    assert not bad, "error messages name options that no freipose command has:\n" + "\n".join(bad)


def test_every_config_key_in_an_error_message_exists(messages):
    keys = config_keys()
    bad = [
        f"{m.where}: {table}.{key}"
        for m in messages
        for table, key in KEY.findall(m.text)
        if key not in FILE_SUFFIXES and key not in keys[table]
    ]
    assert not bad, "error messages name config keys that do not exist:\n" + "\n".join(bad)


def test_keyword_argument_hints_name_the_option_too(messages):
    bad = [
        f"{m.where}: pass {kw}="
        for m in messages
        for kw in KWARG.findall(m.text)
        if not (LONG.search(m.text) or KEY.search(m.text))
    ]
    assert not bad, (
        "error messages tell the user to pass a Python keyword argument without the "
        "command-line option or config key that does the same:\n" + "\n".join(bad)
    )
