"""The paper's task sequences (appendix A), verbatim, our held-out sets, and a family's training sequence and
held-out tasks as task pytrees."""

from __future__ import annotations

import jax
import numpy as np

from jcomps.envs.base import Family
from jcomps.envs.registry import make

SEQUENCE_KINDS = ("stationary", "non-stationary")

# Ant Goal and Ant Direction: angles in degrees (0 = +x, 90 = +y). Point Goal reuses them for its goals.
ANT_ANGLES_DEG = (
    -171, 9, -162, 18, -153, 27, -144, 36, -135, 45, -126, 54, -117, 63, -108, 72, -99, 81, -90, 90,
    -81, 99, -72, 108, -63, 117, -54, 126, -45, 135, -36, 144, -27, 153, -18, 162, -9, 171, 0, 180,
)

# Half-Cheetah Velocity: goal velocities along x in m/s.
CHEETAH_VELOCITIES = (
    -2.66, 0.14, -2.52, 0.28, -2.38, 0.42, -2.24, 0.56, -2.1, 0.7, -1.96, 0.84, -1.82, 0.98, -1.68, 1.12,
    -1.54, 1.26, -1.4, 1.4, -1.26, 1.54, -1.12, 1.68, -0.98, 1.82, -0.84, 1.96, -0.7, 2.1, -0.56, 2.24,
    -0.42, 2.38, -0.28, 2.52, -0.14, 2.66, 0.0, 2.8,
)

# Held-out tasks (our choice): never in the training lists. The paper's angles are every multiple of 9
# degrees in (-180, 180], so held-out angles sit between them; the held-out velocities sit between the
# paper's multiples of 0.14 m/s.
HELD_OUT_ANGLES_DEG = (-157.5, -112.5, -67.5, -22.5, 22.5, 67.5, 112.5, 157.5)
HELD_OUT_VELOCITIES = (-2.59, -1.89, -1.19, -0.49, 0.49, 1.19, 1.89, 2.59)


def _family(family: Family | str) -> Family:
    return make(family) if isinstance(family, str) else family


def sequence_values(family: Family | str, kind: str = "non-stationary", seed: int = 0,
                    num_tasks: int | None = None, tasks=None) -> np.ndarray:
    """Task parameter values of a training sequence, f32[num_tasks].

    ``non-stationary`` is the paper's fixed order; ``stationary`` is the same list shuffled by ``seed``.
    ``num_tasks`` (default: the whole list) takes a prefix. ``tasks``: a list of the family's task names or values
    (``Family.parse_values``, e.g. ``["P-3", "H-11"]`` on MetaWorld) that replaces the family's list (a run's
    ``--tasks``); empty or None: the family's list.
    """
    family = _family(family)
    if kind not in SEQUENCE_KINDS:
        raise ValueError(f"unknown sequence kind {kind!r}; allowed: {', '.join(SEQUENCE_KINDS)}")
    if tasks is not None and len(tasks):
        values = family.parse_values([str(t) for t in tasks])
    else:
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


def task_at(family: Family | str, index: int, kind: str = "non-stationary", seed: int = 0, tasks=None):
    """Task number ``index`` (0-based) of a training sequence, as an unstacked task pytree."""
    family = _family(family)
    values = sequence_values(family, kind, seed, tasks=tasks)
    if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not 0 <= index < len(values):
        raise IndexError(f"task index must be an integer in [0, {len(values) - 1}] for {family.name}, got {index!r}")
    return jax.tree.map(lambda x: x[0], family.tasks(values[index:index + 1]))


def held_out(family: Family | str):
    """The family's held-out tasks (never trained on), stacked on a leading task axis."""
    family = _family(family)
    return family.tasks(family.held_out_values)
