"""Continual-learning methods, registered by name; every one implements ``jcomps.methods.base.Method``."""

from __future__ import annotations

import dataclasses

from jcomps import ppo
from jcomps.envs.base import Family
from jcomps.methods import comps, ppo_tl
from jcomps.methods.base import Method, TaskMetrics

# name -> (config class, constructor(family, config, on_iteration, on_meta_step) -> Method)
REGISTRY = {
    "ppo_tl": (ppo_tl.PPOTLConfig, ppo_tl.make),
    "ppo": (ppo_tl.PPOTLConfig, ppo_tl.make_scratch),
    "comps": (comps.CoMPSConfig, comps.make),
    "gmps_ppo": (comps.GMPSPPOConfig, comps.make_gmps_ppo),
}
METHODS = tuple(REGISTRY)


def config_class(name: str):
    """The config dataclass of method ``name``."""
    if name not in REGISTRY:
        raise ValueError(f"unknown method {name!r}; allowed: {', '.join(METHODS)}")
    return REGISTRY[name][0]


def default_config(name: str, family: Family | str):
    """Method ``name``'s default config on ``family``: its registered defaults with the family's calibrated PPO
    settings (``jcomps.ppo.FAMILY_DEFAULTS``) for the RL step."""
    config = config_class(name)()
    family_name = family if isinstance(family, str) else family.name
    return dataclasses.replace(config, ppo=ppo.family_config(family_name, config.ppo))


def make(name: str, family: Family, config=None, on_iteration=None, on_meta_step=None) -> Method:
    """Method ``name`` (one of ``METHODS``) on ``family`` with ``config`` (default: ``default_config(name,
    family)``, the paper's defaults with the family's calibrated PPO settings).

    ``on_iteration(context, iteration, success_rate, mean_return)``: optional host function called after every
    RL iteration (see ``ppo.rl_step``), with the ``context`` passed to ``learn_task``.
    ``on_meta_step(context, step, steps, loss)``: likewise after every outer update of a meta-training phase
    (``meta.meta_train``; methods without one ignore it).
    """
    cls = config_class(name)
    if config is None:
        config = default_config(name, family)
    if not isinstance(config, cls):
        raise TypeError(f"method {name!r} takes a {cls.__name__}, got {type(config).__name__}")
    return REGISTRY[name][1](family, config, on_iteration, on_meta_step)


__all__ = ["METHODS", "Method", "REGISTRY", "TaskMetrics", "config_class", "default_config", "make"]
