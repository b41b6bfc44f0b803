"""Pickling support for frozen dataclasses that hold read-only mappings.

``types.MappingProxyType`` cannot be pickled, yet DataLoader workers and process pools
pickle our domain objects. ``PicklableFrozen.__reduce__`` rebuilds an object from its
fields (mappings as plain dicts), so ``__post_init__`` validates it again on load.
"""

from __future__ import annotations

from dataclasses import fields
from types import MappingProxyType
from typing import Any


def _rebuild(cls: type, kwargs: dict[str, Any]) -> Any:
    return cls(**kwargs)


class PicklableFrozen:
    """Mixin for frozen dataclasses with ``MappingProxyType`` fields."""

    def __reduce__(self) -> tuple[Any, ...]:
        kwargs = {}
        for f in fields(self):  # type: ignore[arg-type]
            v = getattr(self, f.name)
            kwargs[f.name] = dict(v) if isinstance(v, MappingProxyType) else v
        return _rebuild, (type(self), kwargs)
