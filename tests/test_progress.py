"""Progress lines when standard error is not a terminal; tqdm bars in a terminal."""

from __future__ import annotations

import io
import sys
import time

import pytest

from freipose.progress import LineProgress, progress_bar


def test_line_progress_prints_every_interval_and_at_the_end() -> None:
    out = io.StringIO()
    bar = LineProgress(total=4, desc="train voxel", unit="step", interval=0.05, stream=out)
    bar.update(1)  # no line yet: the interval has not passed
    assert out.getvalue() == ""
    time.sleep(0.06)
    bar.set_postfix(loss=0.012345, refresh=False)
    bar.update(1)
    bar.update(2)
    bar.close()
    bar.close()
    lines = out.getvalue().splitlines()
    assert lines[0].startswith("train voxel: 2/4 step (50%), 0:00 elapsed")
    assert "left" in lines[0] and lines[0].endswith("loss=0.01235")
    assert lines[1].startswith("train voxel: 4/4 step (100%)")
    assert len(lines) == 2


def test_line_progress_iterates_and_resumes() -> None:
    out = io.StringIO()
    bar = LineProgress(iter(range(3)), desc="d", unit="frame", initial=5, interval=1e9, stream=out)
    assert list(bar) == [0, 1, 2]
    assert out.getvalue().strip() == "d: 8 frame, 0:00 elapsed"  # no total: a count


def test_progress_bar_gives_lines_off_a_terminal(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    assert isinstance(progress_bar(total=3, desc="x"), LineProgress)
    assert progress_bar(total=3, disable=True).disable


def test_progress_bar_is_tqdm_in_a_terminal(monkeypatch: pytest.MonkeyPatch) -> None:
    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    monkeypatch.setattr(sys, "stderr", Tty())
    from tqdm import tqdm

    bar = progress_bar(total=3, desc="x")
    assert isinstance(bar, tqdm) and not bar.disable
    bar.close()
