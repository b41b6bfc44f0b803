r"""MkDocs hook: the generated CLI reference shows each help text as ``--help`` prints it.

mkdocs-click copies a command's help text into the page as Markdown. Three things of
click's help texts then go wrong, and are fixed here on the generated lines:

- the indented lines that click prints unwrapped after a ``\b`` line (examples,
  workflows) become a code block instead of one run-on paragraph;
- ``<session>`` and similar placeholders are escaped (as HTML they would vanish), and so
  are the ``*`` of globs (``cams/*.mp4``), which would start emphasis;
- the default of an option without one, click's ``Sentinel.UNSET`` (click >= 8.3, which
  mkdocs-click 0.9 prints as it is), is left empty.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from typing import Any

import mkdocs_click._extension as click_extension

_CODE_SPAN = re.compile(r"(`[^`]*`)")
_UNSET = "`Sentinel.UNSET`"


_GLOB_STAR = re.compile(r"(?<=/)\*|\*(?=\.)")


def _escape(line: str) -> str:
    """``<``, ``>`` and the ``*`` of globs escaped outside the line's code spans."""
    parts = _CODE_SPAN.split(line)
    for i in range(0, len(parts), 2):  # even parts lie outside code spans
        text = parts[i].replace("<", "&lt;").replace(">", "&gt;")
        parts[i] = _GLOB_STAR.sub(r"\\*", text)
    return "".join(parts)


def tidy(lines: Iterable[str]) -> Iterator[str]:
    """The generated Markdown lines, with the fixes of the module docstring."""
    in_fence = in_verbatim = False
    for line in lines:
        if in_verbatim:
            if line.startswith("  "):
                yield line
                continue
            in_verbatim = False
            yield "```"
        if line.startswith("```"):
            in_fence = not in_fence
            yield line
        elif in_fence:
            yield line
        elif line.startswith("  "):
            in_verbatim = True
            yield from ("", "```text", line)
        else:
            yield _escape(line.replace(_UNSET, ""))
    if in_verbatim:
        yield "```"


_generate = click_extension.make_command_docs


def _make_command_docs(*args: Any, **kwargs: Any) -> Iterator[str]:
    return tidy(_generate(*args, **kwargs))


def on_startup(**_: Any) -> None:
    """Route mkdocs-click's page generation through :func:`tidy` (once per build process)."""
    if click_extension.make_command_docs is _generate:
        click_extension.make_command_docs = _make_command_docs
