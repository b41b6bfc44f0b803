"""Shared helpers for CLI commands: turning library errors into ClickExceptions."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import click


@contextlib.contextmanager
def user_errors(*extra: type[BaseException]) -> Iterator[None]:
    """Turn the errors a user can fix (bad files, bad values) into ``click.ClickException``.

    Library code raises ``ValueError`` (and subclasses such as the format errors),
    ``FileNotFoundError`` or ``KeyError`` with a message that says what was expected, what
    was found and how to fix it; the CLI shows that message without a traceback.
    """
    try:
        yield
    except click.ClickException:
        raise
    except (ValueError, FileNotFoundError, KeyError, *extra) as exc:
        msg = exc.args[0] if isinstance(exc, KeyError) and exc.args else str(exc)
        raise click.ClickException(str(msg)) from exc
