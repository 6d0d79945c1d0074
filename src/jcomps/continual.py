"""The continual loop: a method learns a sequence of tasks one at a time, as a ``lax.scan`` over tasks.

Seeds are a ``vmap`` axis: ``run_seeds`` runs S independent seeds (each with its own task order if the
sequences differ) in one compiled program.
"""

from __future__ import annotations

from typing import Any, Callable, Optional

import jax
import jax.numpy as jnp

from jcomps.methods.base import Method, TaskMetrics

ProgressFn = Callable[[jax.Array, jax.Array, TaskMetrics], None]


def run_tasks(method: Method, state: Any, tasks, progress: Optional[ProgressFn] = None, seed_index=0):
    """Learns ``tasks`` (a task pytree with a leading task axis) in order, starting from ``state``.

    ``learn_task`` is wrapped in ``jax.jit`` so that it is traced once per method and shapes, however long the
    sequence and however it is chunked. ``progress(seed_index, task_index, metrics)``, if given, is called on
    the host after each task through ``jax.debug.callback`` (under ``vmap`` once per seed, in no fixed order;
    ``seed_index`` says which). Returns (final state, TaskMetrics with a leading task axis).
    """
    learn = jax.jit(method.learn_task)

    def body(state, task):
        new_state, metrics = learn(state, task)
        if progress is not None:
            jax.debug.callback(progress, seed_index, getattr(state, "task_index", jnp.int32(-1)), metrics)
        return new_state, metrics

    return jax.lax.scan(body, state, tasks)


def run_sequence(method: Method, tasks, rng: jax.Array, progress: Optional[ProgressFn] = None, seed_index=0):
    """``method.init(rng)`` then ``run_tasks``; returns (final state, TaskMetrics[num_tasks])."""
    return run_tasks(method, method.init(rng), tasks, progress, seed_index)


def run_seeds(method: Method, tasks, rngs: jax.Array, progress: Optional[ProgressFn] = None,
              tasks_per_seed: bool = False):
    """``run_sequence`` vmapped over ``rngs`` (a batch of S keys), jitted as one program.

    ``tasks`` is shared by all seeds, or, with ``tasks_per_seed``, has a leading seed axis (stationary
    sequences shuffled per seed). Returns (states, TaskMetrics) with a leading seed axis.
    """
    fn = jax.vmap(lambda t, r, i: run_sequence(method, t, r, progress, i),
                  in_axes=(0 if tasks_per_seed else None, 0, 0))
    return jax.jit(fn)(tasks, rngs, jnp.arange(rngs.shape[0], dtype=jnp.int32))
