"""Every migration table in one place: how this version reads the run directories older versions wrote.

A run directory records its configs (``run.json``) and its checkpoints. When a config field is added, a run made
before it lacks the field: it takes the field's default, or, where the default differs from what such a run did,
the value it had (``EARLIER_VALUES``, read by ``jcomps.methods.resolve_config`` through ``with_earlier_values``).
When an addition changed what checkpoints hold, such a run can still be reported but not resumed
(``UNRESUMABLE_BEFORE``, ``UNRESUMABLE_EVAL_BEFORE``, and ``FORMAT`` with ``FORMAT_CHANGES``; read by
``jcomps.runner.description.from_json``, which says why). A field that followed another value when None (the RL
step's budget, CoMPS's meta reward scale) was recorded as null before the resolver filled it: reading such a
``run.json`` fills it (``jcomps.methods.with_followed``). A finished entry's raw results (``raw/<entry>.npz``) written
by earlier versions are brought to today's names and fields by ``upgrade_raw`` (``RAW_KEYS_BEFORE``,
``RAW_FILLED_AS_NAN``; read by ``jcomps.runner.results``).
"""

from __future__ import annotations

import copy
from typing import Any, Callable, Mapping

import numpy as np

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


# Raw-results arrays (``raw/<entry>.npz``) of the format before RawResults, by their names then -> their names now;
# keys ``iter.<field>`` were ``task.per_iteration.<field>``.
RAW_KEYS_BEFORE = {"heldout_return": "heldout.mean_return", "heldout_success": "heldout.success_rate"}

# Raw-results arrays added since: name -> the array its shape follows. A file that lacks one gets NaN of that shape
# (the quantity was not measured: the report shows it as missing).
RAW_FILLED_AS_NAN = {
    "task.per_iteration.value_ev": "task.per_iteration.valid",  # the critic's explained variance
    **{f"task.meta.{part}.inner_gain": f"task.meta.{part}.bc_loss" for part in ("steps", "start", "end")},
}


def upgrade_raw(arrays: Mapping[str, np.ndarray]) -> dict:
    """A raw-results file's arrays (name -> array) as this version names them, with the arrays added since filled
    (``RAW_FILLED_AS_NAN``; iterations-to-success on the held-out tasks, not measured before RawResults, as 0 and
    unsolved)."""
    out = dict(arrays)
    if "task.per_iteration.valid" not in out:  # the format before RawResults
        out = {}
        for key, value in arrays.items():
            if key.startswith("iter."):
                key = "task.per_iteration." + key[len("iter."):]
            out[RAW_KEYS_BEFORE.get(key, key)] = value
        shape = out["heldout.mean_return"].shape[:3]  # [S, P, H]
        out.setdefault("heldout.iterations", np.zeros(shape, np.int32))
        out.setdefault("heldout.solved", np.zeros(shape, bool))
    for key, like in RAW_FILLED_AS_NAN.items():
        if key not in out and like in out:
            out[key] = np.full(np.shape(out[like]), np.nan, np.float32)
    return out
