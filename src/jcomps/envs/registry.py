"""The families' registry: a family is found by name, built once on first use, and registered with its
calibrated settings (``jcomps.envs.catalogue`` registers the families jcomps ships)."""

from __future__ import annotations

import functools
import types
from typing import Any, Callable, Mapping, NamedTuple, Optional

from jcomps.envs.base import Family
from jcomps.registry import Registry

Settings = Mapping[str, Mapping[str, Any]]
"""A family's calibrated settings: config part (``"ppo"``, ``"meta"``, ``"pearl"``, ...) -> {field: value}."""


class Registered(NamedTuple):
    """A registered family: ``make() -> Family`` (called once, on first use) and its calibrated ``settings``."""

    make: Callable[[], Family]
    settings: Settings


REGISTRY: Registry[Registered] = Registry("family")


def register(name: str, make_fn: Callable[[], Family], settings: Optional[Settings] = None) -> None:
    """Registers family ``name``: ``make_fn()`` builds it (its ``name`` must be ``name``), ``settings`` are its
    calibrated config settings by part. A name can be registered once."""
    frozen = {part: types.MappingProxyType(dict(fields)) for part, fields in (settings or {}).items()}
    REGISTRY.add(name, Registered(make_fn, types.MappingProxyType(frozen)))


def names() -> tuple[str, ...]:
    """The registered families' names, in registration order."""
    return REGISTRY.names()


def settings(family: Family | str, part: str) -> Mapping[str, Any]:
    """Family ``family``'s calibrated settings for config part ``part`` ({} if it has none)."""
    return REGISTRY.lookup(family if isinstance(family, str) else family.name).settings.get(part, {})


def settings_by_field() -> dict[str, dict[str, Any]]:
    """{field: {family: value}}: every registered family's calibrated settings by field name (all parts), as the
    command line's help shows them."""
    out: dict[str, dict[str, Any]] = {}
    for name in names():
        for fields in REGISTRY.lookup(name).settings.values():
            for field, value in fields.items():
                out.setdefault(field, {})[name] = value
    return out


@functools.cache
def make(name: str) -> Family:
    """The family called ``name`` (one of ``names()``); the same object on every call."""
    family = REGISTRY.lookup(name).make()
    if family.name != name:
        raise ValueError(f"family registered as {name!r} is called {family.name!r}")
    return family
