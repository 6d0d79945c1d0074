"""A registry by name: what families (``jcomps.envs``) and methods (``jcomps.methods``) are found through."""

from __future__ import annotations

from typing import Generic, TypeVar

T = TypeVar("T")


class Registry(dict, Generic[T]):
    """{name: entry} of one kind of thing (``kind``: "family", "method"), filled by ``add``, read by ``lookup``."""

    def __init__(self, kind: str):
        super().__init__()
        self.kind = kind

    def add(self, name: str, entry: T) -> None:
        """Registers ``entry`` as ``name``; a name can be registered once."""
        if name in self:
            raise ValueError(f"{self.kind} {name!r} is already registered")
        self[name] = entry

    def names(self) -> tuple[str, ...]:
        """The registered names, in registration order."""
        return tuple(self)

    def lookup(self, name: str) -> T:
        """The entry registered as ``name``; ValueError naming the allowed names otherwise."""
        if name not in self:
            raise ValueError(f"unknown {self.kind} {name!r}; allowed: {', '.join(self)}")
        return self[name]
