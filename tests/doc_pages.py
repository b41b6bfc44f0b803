"""Documentation pages as the tests run them: their commands, after substitutions.

The fenced ``bash`` blocks of a page are run as written (``freipose ...`` lines, backslash
continuations joined, globs expanded in the working folder) after substitutions that
adapt sizes to a test (frames, training steps, the tiny network); a ``toml`` block after
``<!-- file: NAME -->`` is written to NAME. Each substitution must match the page, so the
tests follow it when it changes.

``docs/own-data.md`` with :data:`SUBSTITUTIONS` runs once per test session
(``own_data_run`` in ``conftest.py``): ``tests/test_own_data.py`` checks what its
commands write, and ``tests/nn/test_unlabeled_tutorial.py`` continues from there with
``docs/tutorials/few-labels.md``. ``tests/demo/test_docs_tutorials.py`` runs the pages
that start from the demo.
"""

from __future__ import annotations

from pathlib import Path

from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.testing import fenced_blocks, freipose_commands

DOC = Path(__file__).resolve().parents[1] / "docs" / "own-data.md"

#: ``docs/own-data.md`` shrunk to a test's sizes
SUBSTITUTIONS = {
    "--frames 600": "--frames 40",
    "--gap 30": "--gap 3",
    'preset = "small"': 'preset = "tiny"',
    "steps = 600": "steps = 2",
    "checkpoint_every = 200": "checkpoint_every = 2",
    "eval_every = 200": "eval_every = 2",
    "steps = 300": "steps = 2\ninput_size = 64\nwidth = 0.25\nbatch_size = 2",
    "--n 20": "--n 3",
}


def substituted(path: Path, substitutions: dict[str, str]) -> str:
    """The page's text after ``substitutions``, in order; each must match the page."""
    text = path.read_text(encoding="utf-8")
    for old, new in substitutions.items():
        assert old in text, f"{path.name} no longer holds {old!r}: update the test"
        text = text.replace(old, new)
    return text


def run_blocks(text: str, runner: CliRunner, words: int | None = 2) -> tuple[dict[str, str], int]:
    """Run the fenced blocks of ``text`` in the current folder.

    Args:
        text: the page (after :func:`substituted`).
        runner: the click runner that invokes the commands.
        words: the outputs are keyed by the commands' first ``words`` words (None: the
            whole command line); outputs of commands with the same key are concatenated.

    Returns:
        The outputs by key, and how many commands ran.
    """
    outputs: dict[str, str] = {}
    ran = 0
    for lang, body, name in fenced_blocks(text):
        if lang == "toml" and name:
            Path(name).write_text(body, encoding="utf-8")
        if lang != "bash":
            continue
        for args in freipose_commands(body):
            res = runner.invoke(cli, args)
            assert res.exit_code == 0, f"freipose {' '.join(args)}\n{res.output}"
            key = " ".join(args[:words])
            outputs[key] = outputs.get(key, "") + res.output
            ran += 1
    return outputs, ran
