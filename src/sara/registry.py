"""Name -> backend registries: one small mechanism behind every seam (features, matchers,
global descriptors, pair sources, executors).

Entries are "module:attribute" strings, imported on first use, so a backend's heavy
dependencies (torch, kornia, ray) load only when that backend is chosen. Tests and plugins add
entries with :meth:`Registry.register`, which also takes the object itself.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterator
from typing import Any, Generic, TypeVar

T = TypeVar("T")


class Registry(Generic[T]):
    """A mapping of backend names to objects of one kind (usually factories)."""

    def __init__(self, kind: str, entries: dict[str, str | Any] | None = None) -> None:
        self.kind = kind
        self._entries: dict[str, str | Any] = dict(entries or {})

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def names(self) -> list[str]:
        return list(self._entries)

    def register(self, name: str, target: str | Any) -> None:
        """Add (or replace) a backend: a "module:attribute" string or the object itself."""
        self._entries[name] = target

    def unregister(self, name: str) -> None:
        self._entries.pop(name, None)

    def get(self, name: str) -> T:
        """The backend called `name`; an unknown name raises ValueError listing the valid ones."""
        if name not in self._entries:
            raise ValueError(f"unknown {self.kind} {name!r}; choose one of: {', '.join(self._entries)}")
        target = self._entries[name]
        if isinstance(target, str):
            module, _, attr = target.partition(":")
            return getattr(importlib.import_module(module), attr)
        return target
