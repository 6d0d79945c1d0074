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

from jcomps.methods import base
from jcomps.methods.base import Method, TaskMetrics, collection, task_slots
from jcomps.methods.catalogue import LADDER, LADDER_FEATURES, METHODS, STANDARDISED_INNER_ADVANTAGES
from jcomps.methods.registry import (EVERY_FAMILY, REGISTRY, Registered, config_class, default_config, make, names,
                                     register, resolve_config, settings_by_field, with_family_settings,
                                     with_followed)

__all__ = ["EVERY_FAMILY", "LADDER", "LADDER_FEATURES", "METHODS", "Method", "REGISTRY", "Registered",
           "STANDARDISED_INNER_ADVANTAGES", "TaskMetrics", "base", "collection", "config_class", "default_config",
           "make", "names", "register", "resolve_config", "settings_by_field", "task_slots", "with_family_settings",
           "with_followed"]
