"""Every migration table in one place: how this version reads the run directories older versions wrote.

A run directory records its configs (``run.json``) and its checkpoints. When a config field is added, a run made
before it lacks the field: it takes the field's default, or, where the default differs from what such a run did,
the value it had (``EARLIER_VALUES``, read by ``jcomps.methods.resolve_config`` through ``with_earlier_values``).
When an addition changed what checkpoints hold, such a run can still be reported but not resumed
(``UNRESUMABLE_BEFORE``, ``UNRESUMABLE_EVAL_BEFORE``, and ``FORMAT`` with ``FORMAT_CHANGES``; read by
``jcomps.runner.description.from_json``, which says why).
"""

from __future__ import annotations

import copy
from typing import Any, Callable, Mapping

FORMAT = 3
"""The format of what a run's checkpoints hold beyond its configs, recorded as ``run.json``'s ``format`` (runs
made before it was recorded are format 1); a resume refuses an older one (``FORMAT_CHANGES`` says why)."""
FORMAT_CHANGES = {
    2: "the RL step's per-iteration metrics now hold the critic's explained variance, which its checkpoints lack",
    3: "the per-task metrics now hold the policy's exploration std, entropy and hidden-unit saturation at each "
       "task's start and end, which its checkpoints lack",
}

# Config fields whose addition changed what a method's state holds, so that a run made before them cannot be
# resumed by this version whatever the options (its checkpoints no longer fit): field path within a method's
# config -> why.
UNRESUMABLE_BEFORE = {
    "meta.value_init": "CoMPS's meta step now keeps one value network per task and starts a new task's from the RL "
                       "step's critic",
    "context_source": "PEARL now keeps oyster's encoder buffers and weighs its KL per task",
    "kb_statistics": "PNC's knowledge base now pools its observation statistics over tasks",
    "meta.outer_loss": "the meta step now reports the inner step's gain per task slot, which its checkpoints lack",
}

# The same for evaluation fields, whose addition changed the metrics that checkpoints hold.
UNRESUMABLE_EVAL_BEFORE = dict.fromkeys(
    ("learnt_eval", "learnt_episodes"),
    "its checkpoints lack the evaluations of the learnt tasks behind forgetting and average performance")

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
