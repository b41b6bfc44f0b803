"""Progress reporting for long jobs: a tqdm bar in a terminal, a line every N seconds elsewhere.

``progress_bar`` is the one way FreiPose shows progress. In a terminal it is a tqdm bar.
When standard error is not a terminal (``nohup``, a pipe, a cluster job's log file) a bar
would print nothing readable for minutes, so the same calls print a plain line instead,
at most every ``FREIPOSE_PROGRESS_SECONDS`` seconds (default 15) and once at the end::

    train voxel: 120/300 step (40%), 2:31 elapsed, 3:46 left, loss=0.0123

The returned object has the part of tqdm's interface FreiPose uses: iteration,
``update``, ``set_postfix``, ``set_postfix_str``, ``close``, ``n``, ``total``, ``disable``
and use as a context manager.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Iterable, Iterator
from typing import IO, Any

ENV_SECONDS = "FREIPOSE_PROGRESS_SECONDS"
DEFAULT_SECONDS = 15.0


def line_interval() -> float:
    """Seconds between two progress lines when standard error is not a terminal."""
    try:
        return max(0.0, float(os.environ.get(ENV_SECONDS, DEFAULT_SECONDS)))
    except ValueError:
        return DEFAULT_SECONDS


def _clock(seconds: float) -> str:
    s = int(round(seconds))
    h, rest = divmod(s, 3600)
    m, s = divmod(rest, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


class LineProgress:
    """A tqdm stand-in that prints one line per interval (for logs and pipes).

    Args:
        iterable: items to iterate over (optional).
        total: the number of units; ``len(iterable)`` when omitted and available.
        desc: what is progressing (the line's prefix).
        unit: the unit's name.
        initial: units already done (a resumed job).
        interval: seconds between lines.
        stream: where lines go [default: standard error].
    """

    def __init__(
        self,
        iterable: Iterable[Any] | None = None,
        *,
        total: float | None = None,
        desc: str = "",
        unit: str = "it",
        initial: float = 0,
        interval: float | None = None,
        stream: IO[str] | None = None,
    ):
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)  # type: ignore[arg-type]
        self.iterable, self.total, self.desc, self.unit = iterable, total, desc, unit
        self.n = initial
        self.initial = initial
        self.disable = False
        self.interval = line_interval() if interval is None else interval
        self.stream = stream
        self.postfix = ""
        self._t0 = time.monotonic()
        self._last = self._t0
        self._closed = False
        self._printed_n: float | None = None

    def _line(self) -> str:
        elapsed = time.monotonic() - self._t0
        head = f"{self.desc}: " if self.desc else ""
        if self.total:
            pct = 100.0 * self.n / self.total
            text = f"{head}{self.n:g}/{self.total:g} {self.unit} ({pct:.0f}%), "
            text += f"{_clock(elapsed)} elapsed"
            rate = (self.n - self.initial) / elapsed if elapsed > 0 else 0.0
            if rate > 0 and self.n < self.total:
                text += f", {_clock((self.total - self.n) / rate)} left"
        else:
            text = f"{head}{self.n:g} {self.unit}, {_clock(elapsed)} elapsed"
        return text + (f", {self.postfix}" if self.postfix else "")

    def _emit(self) -> None:
        stream = self.stream if self.stream is not None else sys.stderr
        print(self._line(), file=stream, flush=True)
        self._last = time.monotonic()
        self._printed_n = self.n

    def update(self, n: float = 1) -> None:
        """Advance by ``n`` units; print a line when the interval has passed."""
        self.n += n
        if time.monotonic() - self._last >= self.interval:
            self._emit()

    def set_postfix(
        self, ordered_dict: dict[str, Any] | None = None, refresh: bool = True, **kwargs: Any
    ) -> None:
        """Show ``key=value`` pairs (numbers with 4 significant digits) after the counts."""
        items = {**(ordered_dict or {}), **kwargs}
        self.postfix = ", ".join(
            f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in items.items()
        )

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        """Show ``s`` after the counts."""
        self.postfix = s

    def set_description(self, desc: str | None = None, refresh: bool = True) -> None:
        """Change the line's prefix."""
        self.desc = desc or ""

    def refresh(self) -> None:
        """Nothing to redraw: lines are printed by ``update`` and ``close``."""

    def close(self) -> None:
        """Print the final line (unless nothing changed since the last one)."""
        if self._closed:
            return
        self._closed = True
        if self._printed_n != self.n:
            self._emit()

    def __iter__(self) -> Iterator[Any]:
        if self.iterable is None:
            raise TypeError("this progress line was made without an iterable")
        try:
            for item in self.iterable:
                yield item
                self.update(1)
        finally:
            self.close()

    def __enter__(self) -> LineProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _is_terminal(stream: IO[str]) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def progress_bar(
    iterable: Iterable[Any] | None = None,
    *,
    total: float | None = None,
    desc: str = "",
    unit: str = "it",
    initial: float = 0,
    leave: bool = True,
    disable: bool | None = None,
) -> Any:
    """A progress bar in a terminal, progress lines elsewhere, nothing when disabled.

    Args:
        iterable: items to iterate over (optional).
        total: the number of units.
        desc: what is progressing.
        unit: the unit's name.
        initial: units already done (a resumed job).
        leave: keep the terminal bar after it closes.
        disable: True shows nothing; False or None shows a bar or lines (as tqdm's
            ``disable=None``, except that a non-terminal gets lines instead of silence).

    Returns:
        A ``tqdm`` bar or a ``LineProgress`` with the same methods.
    """
    from tqdm import tqdm

    if disable:
        return tqdm(iterable, total=total, desc=desc, unit=unit, initial=initial, disable=True)
    if _is_terminal(sys.stderr):
        return tqdm(
            iterable, total=total, desc=desc, unit=unit, initial=initial, leave=leave,
            dynamic_ncols=True,
        )  # fmt: skip
    return LineProgress(iterable, total=total, desc=desc, unit=unit, initial=initial)
