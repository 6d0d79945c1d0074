"""The members of a compiled program and their random streams.

A program runs its members side by side: ``vmap`` over the members of a device, ``shard_map`` over devices (the
member axis). Members are the seeds, or with a hyperparameter grid (``jcomps.runner.grid``) the program's grid points ×
the seeds, point-major, padded up to a multiple of the devices used (every device gets the same number; padding
members cost no wall time and are dropped from every result).

Each seed's key is split into separately salted roots for the method (``method_keys``) and for the evaluations
(``eval_keys``), so that an evaluation never changes what a method learns.
"""

from __future__ import annotations

from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np

from jcomps import envs
from jcomps.runner import grid as grids


def num_devices(seeds: int, available: Optional[int] = None) -> int:
    """How many devices ``seeds`` seeds (or members) are spread over: all available ones, at most one per seed;
    with several processes (``jcomps.runner.distributed``) every device of every process, since each process must hold
    members of the program (fewer members than devices are padded)."""
    if available is None and jax.process_count() > 1:
        return jax.device_count()
    return max(1, min(seeds, available or jax.device_count()))


def padded_seeds(seeds: int, devices: int) -> int:
    """Seeds actually run: ``seeds`` rounded up to a multiple of ``devices`` (every device gets the same number;
    the extra seeds, run + ``seeds``, ..., cost no wall time and are dropped from the results)."""
    return -(-seeds // devices) * devices


def layout(spec: grids.ProgramSpec, seeds: int, first_seed: int, devices: int) -> tuple[list, list, dict]:
    """The member layout of a program: (grid point index, seed) of every member, and the traced values
    ({field: f32[members]}). Point-major: member ``p * seeds + s`` is point ``p`` with seed ``first_seed + s``;
    padding members (up to a multiple of ``devices``) repeat point 0 with the next seeds, so without a grid the
    members are the seeds, in order."""
    real = len(spec.points) * seeds
    padded = padded_seeds(real, devices)
    point = [m // seeds for m in range(real)] + [0] * (padded - real)
    extra = first_seed + seeds
    seed = [first_seed + m % seeds for m in range(real)] + list(range(extra, extra + padded - real))
    hparams = {f: np.asarray([dict(spec.points[p].values)[f] for p in point], np.float32) for f in spec.traced}
    return point, seed, hparams


def task_sequences(family: envs.Family, kind: str, seeds: list[int], num_tasks: int, tasks=None):
    """Every member's task sequence on the host, Task [len(seeds), num_tasks, ...]: member ``m`` gets the
    ``kind`` sequence of seed ``seeds[m]`` (``envs.sequence_values``, of the family's list or of ``tasks``; a
    stationary order is shuffled by the seed)."""
    orders = {s: envs.sequence_values(family, kind, s, num_tasks, tasks) for s in sorted(set(seeds))}
    values = np.stack([orders[s] for s in seeds])
    return jax.tree.map(lambda x: x.reshape((len(seeds), num_tasks) + x.shape[1:]), family.tasks(values.reshape(-1)))


# The method's and the evaluations' random streams come from separately salted roots of each seed's key. With
# jax's partitionable threefry ``fold_in(k, 1)`` equals ``split(k)[1]``, so evaluation keys folded from the
# method's own root could coincide with keys the method draws.
METHOD_SALT, EVAL_SALT = 0x6D657468, 0x6576616C  # "meth", "eval"


def _salted(seeds: list[int], *salts: int) -> jax.Array:
    """Each seed's key folded with ``salts`` in turn: u32[len(seeds), 2] (raw PRNG keys)."""
    def one(seed):
        key = jax.random.PRNGKey(seed)
        for salt in salts:
            key = jax.random.fold_in(key, salt)
        return key

    return jax.vmap(one)(jnp.asarray(seeds, jnp.uint32))


def method_keys(seeds: list[int]) -> jax.Array:
    """Each seed's key for ``method.init`` (everything the method draws descends from it)."""
    return _salted(seeds, METHOD_SALT)


# The evaluations' streams under each seed's evaluation root (``eval_keys``): one for the evaluations of learnt
# tasks (backward transfer, each task right after it is learnt and at every later evaluation), and one per
# measurement of the held-out meta-test: measurement m (0: the initial policies, c + 1: after chunk c) draws from
# HELDOUT_STREAM + m.
TASKS_STREAM = 1
HELDOUT_STREAM = 1000


def eval_keys(seeds: list[int], stream: int) -> jax.Array:
    """Each seed's key of evaluation stream ``stream`` (``task_eval_keys``, ``heldout_keys``)."""
    return _salted(seeds, EVAL_SALT, stream)


def task_eval_keys(seeds: list[int]) -> jax.Array:
    """Each seed's key of the learnt tasks' evaluations: backward transfer (folded per task and previous task,
    ``continual.evaluate_task``) and, folded with ``continual.LEARNT_SALT``, every evaluation of a learnt task."""
    return eval_keys(seeds, TASKS_STREAM)


def heldout_keys(seeds: list[int], measurement: int) -> jax.Array:
    """Each seed's key of held-out measurement ``measurement`` (0: the initial policies, c + 1: after chunk c)."""
    return eval_keys(seeds, HELDOUT_STREAM + measurement)
