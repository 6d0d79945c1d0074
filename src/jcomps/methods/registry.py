"""The methods' registry: a method is found by name, as a constructor and its default config *instance*, with its
own settings per family; ``default_config`` and ``resolve_config`` build a method's config from its layers
(``jcomps.methods.catalogue`` registers the methods jcomps ships)."""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Mapping, NamedTuple, Optional

from jcomps import configs, envs, migrations
from jcomps.envs.base import Family
from jcomps.methods.base import Method, task_slots
from jcomps.progress import ProgressFn
from jcomps.registry import Registry


class Registered(NamedTuple):
    """A registered method.

    Attributes:
      default: its default config (an instance of its config dataclass).
      make: ``(family, config, progress_fn) -> Method``.
      family_settings: {family: {part: {field: value}}}, the method's own settings, put over the family's
        calibrated ones (``jcomps.envs.settings``); ``part`` names a config part as ``jcomps.envs.settings`` does
        (``"ppo"``, ``"meta"``). The key ``EVERY_FAMILY`` holds the fields that define the method on every family
        (``gmps``'s vanilla policy gradient keeps one gradient step per iteration, ``pnc`` its columns' sizes), a
        family's key its calibration there (``gmps`` on Point Goal: its vanilla policy gradient solves nothing at
        the family's reward scale, docs/families.md), applied after ``EVERY_FAMILY``'s.
    """

    default: Any
    make: Callable[..., Method]
    family_settings: Mapping[str, Mapping[str, Mapping[str, Any]]] = {}


EVERY_FAMILY = "every family"
"""The key of ``Registered.family_settings`` whose settings apply on every family."""


REGISTRY: Registry[Registered] = Registry("method")


def register(name: str, default, make_fn: Callable[..., Method],
             family_settings: Optional[Mapping[str, Mapping[str, Mapping[str, Any]]]] = None) -> None:
    """Registers method ``name``: ``default`` is its default config (an instance of its frozen config dataclass),
    ``make_fn(family, config, progress_fn) -> Method`` builds it, ``family_settings`` as ``Registered``'s. The
    runner, reports and ``--set`` find it by name from then on (docs/extending.md). A name can be registered
    once."""
    REGISTRY.add(name, Registered(default, make_fn, dict(family_settings or {})))


def settings_by_field() -> dict[str, dict[str, Any]]:
    """{field: {"family (method.part)": value}}: the methods' own settings (``Registered.family_settings``) by
    field name, as the command line's help shows them beside the families' (``jcomps.envs.settings_by_field``)."""
    out: dict[str, dict[str, Any]] = {}
    for name in names():
        for family, parts in REGISTRY[name].family_settings.items():
            for part, fields in parts.items():
                for field, value in fields.items():
                    out.setdefault(field, {})[f"{family} ({name}.{part})"] = value
    return out


def names() -> tuple[str, ...]:
    """The registered methods' names, in registration order."""
    return REGISTRY.names()


def _registered(name: str) -> Registered:
    return REGISTRY.lookup(name)


def config_class(name: str):
    """The config dataclass of method ``name``."""
    return type(_registered(name).default)


def with_family_settings(config, family: Family | str):
    """``config`` (a config dataclass) with ``family``'s calibrated settings (``jcomps.envs.settings``) put over
    every part of it, itself included, whose class names a ``SETTINGS_PART`` (``PPOConfig``: ``"ppo"``,
    ``MetaConfig``: ``"meta"``, ``PEARLConfig``: ``"pearl"``)."""
    changes = {f.name: with_family_settings(getattr(config, f.name), family) for f in dataclasses.fields(config)
               if dataclasses.is_dataclass(getattr(config, f.name))}
    part = getattr(type(config), "SETTINGS_PART", None)
    if part is not None:
        changes.update(envs.settings(family, part))
    return dataclasses.replace(config, **changes)


def default_config(name: str, family: Family | str):
    """Method ``name``'s default config on ``family``: its registered default with the family's calibrated settings
    (``with_family_settings``), then the method's own settings (``Registered.family_settings``): those for every
    family, then those for this one."""
    entry = _registered(name)
    config = with_family_settings(entry.default, family)
    for key in (EVERY_FAMILY, family if isinstance(family, str) else family.name):
        own = entry.family_settings.get(key, {})
        parts = {part: dataclasses.replace(getattr(config, part), **fields) for part, fields in own.items()}
        config = dataclasses.replace(config, **parts) if parts else config
    return config


def with_followed(config, family: Family | str, keep=frozenset()):
    """``config`` with every field that follows another value when None filled with that value, nested parts first
    (each config class's ``follow(family, keep)``: ``PPOConfig.budget`` the family's default budget, CoMPS's
    ``meta.reward_scale``, ``meta.value_learning_rate`` and ``meta.hold_std`` the RL step's, PEARL's
    ``num_updates``), so that a run's ``run.json`` records the values that ran. ``keep``: the flat field names a
    hyperparameter grid varies; a field following one of them stays None and takes each point's value where it is
    used (``jcomps.methods.comps.meta_config``)."""
    family = envs.make(family) if isinstance(family, str) else family
    keep = frozenset(keep)
    changes = {f.name: with_followed(getattr(config, f.name), family, keep) for f in dataclasses.fields(config)
               if dataclasses.is_dataclass(getattr(config, f.name))}
    config = dataclasses.replace(config, **changes) if changes else config
    follow = getattr(config, "follow", None)
    return follow(family, keep) if follow is not None else config


def resolve_config(name: str, family: Family | str, *, stored: Optional[Mapping] = None,
                   shared: Optional[Mapping] = None, num_tasks: Optional[int] = None,
                   overrides: Optional[Mapping] = None, default=None, grid_fields=frozenset()):
    """Method ``name``'s full config on ``family``, from its layers, each over the ones before:

    1. its registered default (``REGISTRY``);
    2. the family's calibrated settings (``default_config``), apart from the fields of the method's RL step;
    3. ``stored``: the config a run recorded (``run.json``'s ``methods[name]``, on ``--resume`` and in reports);
       fields it lacks (an older run) keep the layers below, apart from those whose default changed since
       (``jcomps.migrations.EARLIER_VALUES``: the run's own value);
    4. ``shared``: {field: value} of the options every method shares (``--learning-rate``), set wherever the field
       occurs in the config, nested parts included;
    5. ``num_tasks``: a config with task slots (``task_slots``) gets one per task, unless layer 3 or 4 gave them;
    6. ``overrides``: {"part.field": value} of this method alone (``--set``; ``configs.parse_overrides``);
    7. the fields that follow another value when None, filled (``with_followed``), but those following one of the
       ``grid_fields`` (the flat field names of the run's grid axes).

    A hyperparameter grid's points are the last layer (``jcomps.runner.grid.points`` over this config). Every layer is
    validated by the config classes' checks (ValueError naming the field); ``overrides``' errors name ``--set``.
    ``default``: layers 1 and 2 when the caller has built them (``default_config(name, family)``).
    """
    config = default_config(name, family) if default is None else default
    if stored:
        config = configs.config_from_dict(config, migrations.with_earlier_values(stored))
    if shared:
        config = configs.with_shared(config, shared)
    given = set(stored or ()) | set(shared or ())
    if num_tasks is not None and task_slots(config) is not None and "max_tasks" not in given:
        config = dataclasses.replace(config, max_tasks=num_tasks)
    config = configs.apply_overrides({name: config}, {name: dict(overrides)} if overrides else {})[name]
    return with_followed(config, family, grid_fields)


def make(name: str, family: Family, config=None, progress_fn: Optional[ProgressFn] = None) -> Method:
    """Method ``name`` (one of ``names()``) on ``family`` with ``config`` (default: ``default_config(name,
    family)``, the paper's defaults with the family's calibrated PPO settings).

    ``progress_fn`` (``jcomps.progress``; e.g. ``progress.host(print)``), if given, gets the metrics of every RL
    iteration and of every outer update of a meta-training phase, with the ``task`` index.
    """
    cls = config_class(name)
    if config is None:
        config = default_config(name, family)
    if not isinstance(config, cls):
        raise TypeError(f"method {name!r} takes a {cls.__name__}, got {type(config).__name__}")
    method = REGISTRY[name].make(family, config, progress_fn)
    if method.adapt is None and not hasattr(config, "ppo"):
        raise TypeError(f"method {name!r} has no PPO config ({cls.__name__}.ppo), so the held-out meta-test cannot "
                        "adapt it with PPO: give its Method an `adapt` (its own meta-test; docs/extending.md)")
    return method
