"""Figures: matplotlib ``Figure`` objects made and saved without pyplot.

Every figure FreiPose writes is made by :func:`new_figure` and written by
:func:`save_figure`. Neither touches pyplot's global state or switches matplotlib's
backend, so library code can draw figures inside an interactive session, a notebook or a
worker thread without side effects.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from matplotlib.figure import Figure

from freipose.io.atomic import atomic_path


def new_figure(figsize: tuple[float, float] = (6.4, 4.8), **kwargs: Any) -> Figure:
    """A new figure of ``figsize`` inches; ``kwargs`` go to :class:`matplotlib.figure.Figure`."""
    return Figure(figsize=figsize, **kwargs)


def save_figure(fig: Figure, path: str | Path, dpi: float = 100, **kwargs: Any) -> Path:
    """Write ``fig`` to ``path`` atomically (format from the suffix) and return the path.

    ``kwargs`` go to :meth:`matplotlib.figure.Figure.savefig` (e.g. ``bbox_inches="tight"``).
    """
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, **kwargs)
    return path
