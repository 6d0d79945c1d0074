"""Continual-learning methods, registered by name; every one implements ``jcomps.methods.base.Method``.

A registered method is a constructor and its default config *instance*: the rungs of the paper's ablation ladder
(appendix "CoMPS Ablation") share CoMPS's config class and constructor and differ only in their defaults.

- ``ppo``: single-task PPO from a random initialisation on every task (no transfer);
- ``ppo_tl``: PPO+TL, PPO on each task with the parameters carried to the next (the paper's baseline);
- ``gmps``: the meta step without importance weights, V-trace or warm start, and GMPS's RL step: vanilla
  on-policy policy gradient (one full-batch gradient step per iteration, no ratio clipping);
- ``gmps_ppo``: as ``gmps`` with our PPO as the RL step;
- ``gmps_ppo_is``: + the importance-sampled inner gradient with the V-trace baseline (no warm start);
- ``gmps_ppo_is_x2``: + twice the skilled data (|D*_i| = 40; no warm start);
- ``comps``: GMPS + PPO + IS + the FTML warm start, CoMPS.

The rungs without the warm start start each meta step from a fresh initialisation (``CoMPSConfig.meta_start``:
GMPS is an offline meta-learner trained from an initialisation, and the authors' continual prototype restarted it
after every task). ``gmps_ppo_last`` and ``gmps_ppo_is_last`` start it from the last meta policy instead, a
stronger baseline than the paper's (the next task's RL step started from that policy, so the start differs from
FTML's only by that task's PPO updates).

Every rung standardises its inner advantages per task or none does (``STANDARDISED_INNER_ADVANTAGES``), so each
rung adds one feature (``LADDER``).

The paper's other continual baselines:

- ``maml_tl``: on-policy MAML in online mode, meta-training on the latest task only (MAML+TL);
- ``pnc``: Progress & Compress: PPO in an active column with lateral adaptors from a frozen knowledge base, then
  distillation into the knowledge base under online EWC;
- ``pearl``: PEARL, the off-policy meta-RL baseline: SAC with a probabilistic context encoder, a replay buffer per
  task slot (its config has no PPO part: the family's PPO settings do not apply to it).
"""

from __future__ import annotations

import copy
import dataclasses
from typing import Any, Callable, Mapping, NamedTuple, Optional

from jcomps import configs, envs
from jcomps.envs.base import Family
from jcomps.methods import base, comps, maml_tl, pearl, pnc, ppo_tl
from jcomps.methods.base import Method, TaskMetrics, collection, task_slots
from jcomps.progress import ProgressFn
from jcomps.registry import Registry
from jcomps.training import meta, ppo


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


# Whether the inner step's advantages are standardised per task (GMPS's ``center_adv``) is one choice for the whole
# ladder, so that no rung changes it: the rung that adds importance sampling changes only the weights and the
# baseline (docs/log.md, "The ablation ladder: one feature per rung", has both readings measured).
STANDARDISED_INNER_ADVANTAGES = False
_META = meta.MetaConfig(normalize_advantages=STANDARDISED_INNER_ADVANTAGES)
_NO_IS = dataclasses.replace(_META, importance_sampling=False, vtrace_baseline=False)
_VANILLA_PG = {"num_updates": 1, "minibatch_size": 0, "surrogate": "vanilla"}
# GMPS's RL step calibrated on Point Goal (docs/families.md, "GMPS's vanilla policy gradient on Point Goal"): no
# learning rate solves task 1 at the family's reward scale of 0.1, 3e-3 is the best at 1. Its meta step stays the
# other rungs' (rewards × 0.1, inner learning rate 0.05: the paper's α = 0.005 on raw rewards): in the RL step's
# units its value heads, copies of a critic that does not fit at scale 1, leave advantages of |A| 50-100 and the
# inner step diverges (the BC loss is infinite from task 2 on, every outer update skipped); in the family's units a
# copied critic is 10x off, so its heads start afresh and fit (EV 0.8; docs/families.md has the three readings).
_GMPS_FAMILY_SETTINGS = {EVERY_FAMILY: {"ppo": _VANILLA_PG},
                         "point_goal": {"ppo": {"reward_scale": 1.0, "learning_rate": 3e-3},
                                        "meta": {"reward_scale": 0.1, "value_init": "random"}}}

REGISTRY: Registry[Registered] = Registry("method")
REGISTRY.update({
    "ppo_tl": Registered(ppo_tl.PPOTLConfig(), ppo_tl.make),
    "ppo": Registered(ppo_tl.PPOTLConfig(), ppo_tl.make_scratch),
    "comps": Registered(comps.CoMPSConfig(meta=_META), comps.make),
    "gmps": Registered(comps.CoMPSConfig(ppo=dataclasses.replace(ppo.PPOConfig(), **_VANILLA_PG), meta=_NO_IS,
                                         warm_start=False), comps.named("gmps"), _GMPS_FAMILY_SETTINGS),
    "gmps_ppo": Registered(comps.CoMPSConfig(meta=_NO_IS, warm_start=False), comps.named("gmps_ppo")),
    "gmps_ppo_is": Registered(comps.CoMPSConfig(meta=_META, warm_start=False), comps.named("gmps_ppo_is")),
    "gmps_ppo_last": Registered(comps.CoMPSConfig(meta=_NO_IS, warm_start=False, meta_start="last"),
                                comps.named("gmps_ppo_last")),
    "gmps_ppo_is_last": Registered(comps.CoMPSConfig(meta=_META, warm_start=False, meta_start="last"),
                                   comps.named("gmps_ppo_is_last")),
    "gmps_ppo_is_x2": Registered(comps.CoMPSConfig(meta=_META, warm_start=False, num_skilled=40),
                                 comps.named("gmps_ppo_is_x2")),
    "maml_tl": Registered(maml_tl.MAMLTLConfig(), maml_tl.make),
    "pnc": Registered(pnc.PNCConfig(), pnc.make,
                      {EVERY_FAMILY: {"ppo": {"hidden_sizes": pnc.PNCConfig().ppo.hidden_sizes}}}),
    "pearl": Registered(pearl.PEARLConfig(), pearl.make),
})

# The paper's ablation ladder (appendix "CoMPS Ablation"): (lower rung, upper rung, the feature the upper adds).
# Every pair differs in the config fields of its feature and in nothing else (tested).
LADDER_FEATURES: dict[str, tuple[str, ...]] = {
    # The RL step and its calibration (a rung's RL step is tuned for it, as the paper tuned each method; where that
    # moves its reward units the meta step keeps the other rungs' units and cannot copy the RL step's critic).
    "PPO as the RL step": ("ppo.num_updates", "ppo.minibatch_size", "ppo.surrogate", "ppo.reward_scale",
                           "ppo.learning_rate", "meta.reward_scale", "meta.value_init"),
    "importance-sampled inner step with the V-trace baseline": ("meta.importance_sampling", "meta.vtrace_baseline"),
    "skilled data x2": ("num_skilled",),
    "FTML warm start": ("warm_start",),
}
LADDER: tuple[tuple[str, str, str], ...] = (
    ("gmps", "gmps_ppo", "PPO as the RL step"),
    ("gmps_ppo", "gmps_ppo_is", "importance-sampled inner step with the V-trace baseline"),
    ("gmps_ppo_is", "gmps_ppo_is_x2", "skilled data x2"),
    ("gmps_ppo_is", "comps", "FTML warm start"),
)
# Config fields added with a default that differs from what runs made before them did: the field's dotted path
# within a method's config -> a function of such a run's stored config (``run.json``'s ``methods[name]``) giving
# the value the run had, or None where the field changed nothing for it (it takes the default).
EARLIER_VALUES: dict[str, Callable[[Mapping], Any]] = {
    # Runs made before this field existed: the rungs without the warm start started their meta step from the last
    # meta policy.
    "meta_start": lambda stored: None if stored.get("warm_start", True) else "last",
    # Runs made before the exploration std had modes learnt it (the families' default is ``fixed`` since issue 58).
    "ppo.std_mode": lambda stored: "learnt",
}


def with_earlier_values(stored: Mapping) -> dict:
    """A stored method config (``run.json``'s ``methods[name]``) with the fields of ``EARLIER_VALUES`` it lacks set
    to the values the run had (a copy; fields it has, and fields whose default it had, are left as they are)."""
    out = copy.deepcopy(dict(stored))
    for path, earlier in EARLIER_VALUES.items():
        *parents, leaf = path.split(".")
        node = out
        for key in parents:
            node = node.get(key) if isinstance(node, dict) else None
        if isinstance(node, dict) and leaf not in node:
            value = earlier(stored)
            if value is not None:
                node[leaf] = value
    return out


METHODS = tuple(REGISTRY)
"""The methods jcomps ships (``names()`` also lists any registered since)."""


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


def resolve_config(name: str, family: Family | str, *, stored: Optional[Mapping] = None,
                   shared: Optional[Mapping] = None, num_tasks: Optional[int] = None,
                   overrides: Optional[Mapping] = None, default=None):
    """Method ``name``'s full config on ``family``, from its layers, each over the ones before:

    1. its registered default (``REGISTRY``);
    2. the family's calibrated settings (``default_config``), apart from the fields of the method's RL step;
    3. ``stored``: the config a run recorded (``run.json``'s ``methods[name]``, on ``--resume`` and in reports);
       fields it lacks (an older run) keep the layers below, apart from those whose default changed since
       (``EARLIER_VALUES``: the run's own value);
    4. ``shared``: {field: value} of the options every method shares (``--learning-rate``), set wherever the field
       occurs in the config, nested parts included;
    5. ``num_tasks``: a config with task slots (``task_slots``) gets one per task, unless layer 3 or 4 gave them;
    6. ``overrides``: {"part.field": value} of this method alone (``--set``; ``configs.parse_overrides``).

    A hyperparameter grid's points are the last layer (``jcomps.runner.grid.points`` over this config). Every layer is
    validated by the config classes' checks (ValueError naming the field); ``overrides``' errors name ``--set``.
    ``default``: layers 1 and 2 when the caller has built them (``default_config(name, family)``).
    """
    config = default_config(name, family) if default is None else default
    if stored:
        config = configs.config_from_dict(config, with_earlier_values(stored))
    if shared:
        config = configs.with_shared(config, shared)
    given = set(stored or ()) | set(shared or ())
    if num_tasks is not None and task_slots(config) is not None and "max_tasks" not in given:
        config = dataclasses.replace(config, max_tasks=num_tasks)
    return configs.apply_overrides({name: config}, {name: dict(overrides)} if overrides else {})[name]


def make(name: str, family: Family, config=None, progress_fn: Optional[ProgressFn] = None) -> Method:
    """Method ``name`` (one of ``METHODS``) on ``family`` with ``config`` (default: ``default_config(name,
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


def env_steps_per_iteration(name: str, family: Family, config=None) -> int:
    """Env steps one iteration of method ``name`` collects with ``config`` (default: its default config)."""
    return base.env_steps_per_iteration(make(name, family, config))


__all__ = ["EARLIER_VALUES", "EVERY_FAMILY", "LADDER", "LADDER_FEATURES", "METHODS", "Method", "collection", "REGISTRY", "Registered",
           "TaskMetrics", "config_class", "default_config", "env_steps_per_iteration", "make", "names", "register",
           "resolve_config", "settings_by_field", "task_slots", "with_earlier_values", "with_family_settings"]
