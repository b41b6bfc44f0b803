"""MkDocs hook: Sphinx roles in docstrings read as plain code in the API pages.

Some docstrings name objects with Sphinx roles (``:func:`name```, ``:mod:`name```).
mkdocstrings renders the backquoted name as code and leaves the role in front of it as
text (``:func: name``); the role is dropped here, the code stays.
"""

from __future__ import annotations

import re
from typing import Any

_ROLE = re.compile(r":(?:py:)?(?:mod|func|class|meth|data|attr|exc|obj|const|ref):(?=<code)")


def on_page_content(html: str, page: Any, **_: Any) -> str:
    """The page's HTML without the Sphinx roles before code spans (API pages only)."""
    if not page.file.src_uri.startswith("reference/api/"):
        return html
    return _ROLE.sub("", html)
