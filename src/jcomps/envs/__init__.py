"""Task families and their task sequences.

Families, by the names used everywhere (CLI included): ``point_goal``, ``cheetah_vel``, ``ant_goal``, ``ant_dir``,
``metaworld``.

>>> fam = make("point_goal")
>>> tasks = sequence(fam, "non-stationary", num_tasks=5)   # stacked task pytree, leading axis 5
"""

from __future__ import annotations

import functools

import jax
import numpy as np

from jcomps.envs.base import EnvState, Family, strong, validate_values

FAMILIES = ("point_goal", "cheetah_vel", "ant_goal", "ant_dir", "metaworld")
SEQUENCE_KINDS = ("stationary", "non-stationary")


@functools.cache
def make(name: str) -> Family:
    """The family called ``name`` (one of ``FAMILIES``); the same object on every call."""
    if name == "point_goal":
        from jcomps.envs import point_goal

        return point_goal.make()
    if name in ("cheetah_vel", "ant_goal", "ant_dir"):
        from jcomps.envs import mujoco

        return mujoco.make(name)
    if name == "metaworld":
        from jcomps.envs import metaworld

        return metaworld.make()
    raise ValueError(f"unknown family {name!r}; allowed: {', '.join(FAMILIES)}")


def _family(family: Family | str) -> Family:
    return make(family) if isinstance(family, str) else family


def sequence_values(family: Family | str, kind: str = "non-stationary", seed: int = 0,
                    num_tasks: int | None = None) -> np.ndarray:
    """Task parameter values of a training sequence, f32[num_tasks].

    ``non-stationary`` is the paper's fixed order; ``stationary`` is the same list shuffled by ``seed``.
    ``num_tasks`` (default: the whole list) takes a prefix.
    """
    family = _family(family)
    if kind not in SEQUENCE_KINDS:
        raise ValueError(f"unknown sequence kind {kind!r}; allowed: {', '.join(SEQUENCE_KINDS)}")
    values = np.asarray(family.task_values, np.float32)
    n = len(values)
    if num_tasks is None:
        num_tasks = n
    if isinstance(num_tasks, bool) or not isinstance(num_tasks, (int, np.integer)) or not 1 <= num_tasks <= n:
        raise ValueError(f"num_tasks must be an integer in [1, {n}] for {family.name}, got {num_tasks!r}")
    if kind == "stationary":
        values = values[np.random.default_rng(seed).permutation(n)]
    return values[:num_tasks]


def sequence(family: Family | str, kind: str = "non-stationary", seed: int = 0, num_tasks: int | None = None):
    """The training sequence as a task pytree stacked on a leading task axis (see ``sequence_values``)."""
    family = _family(family)
    return family.tasks(sequence_values(family, kind, seed, num_tasks))


def task_at(family: Family | str, index: int, kind: str = "non-stationary", seed: int = 0):
    """Task number ``index`` (0-based) of a training sequence, as an unstacked task pytree."""
    family = _family(family)
    values = sequence_values(family, kind, seed)
    if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not 0 <= index < len(values):
        raise IndexError(f"task index must be an integer in [0, {len(values) - 1}] for {family.name}, got {index!r}")
    return jax.tree.map(lambda x: x[0], family.tasks(values[index:index + 1]))


def held_out(family: Family | str):
    """The family's held-out tasks (never trained on), stacked on a leading task axis."""
    family = _family(family)
    return family.tasks(family.held_out_values)


__all__ = [
    "EnvState", "FAMILIES", "Family", "SEQUENCE_KINDS", "held_out", "make", "sequence", "sequence_values",
    "strong", "task_at", "validate_values",
]
