"""The Markdown helpers of freipose.testing that run documented commands."""

import pytest

from freipose.testing import fenced_blocks, freipose_commands


def test_fenced_blocks_keep_order_language_and_file_names():
    text = "intro\n<!-- file: a.toml -->\n```toml\nx = 1\n```\ntext\n```bash\nfreipose demo\n```\n"
    assert fenced_blocks(text) == [("toml", "x = 1\n", "a.toml"), ("bash", "freipose demo\n", None)]


def test_freipose_commands_join_lines_drop_comments_and_expand_globs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "b.mp4").touch()
    (tmp_path / "a.mp4").touch()
    body = "# a comment\nfreipose predict *.mp4 \\\n    -o out  # trailing\nfreipose jobs none*\n"
    expected = [["predict", "a.mp4", "b.mp4", "-o", "out"], ["jobs", "none*"]]
    assert freipose_commands(body) == expected
    with pytest.raises(ValueError, match="only freipose"):
        freipose_commands("ls -l\n")
