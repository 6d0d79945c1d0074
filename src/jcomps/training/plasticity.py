"""What a task's learner starts from and ends with, beyond its return: the exploration std and the saturation of its
policy's hidden units (the continual-RL field's plasticity measures: a policy that enters a task with a collapsed
std, or with tanh units stuck at ±1, has lost the means to learn it; Dohare et al. 2024, Lyle et al. 2023).

Each RL step reports a ``PolicyHealth`` of the policy it starts from and the policy it ends with: the std of the
state-independent Gaussian, its entropy, and per hidden layer the fraction of tanh units that are saturated on the
states the policy visits (those of the task's first iteration for the start, of its last for the end).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jcomps.numerics import masked_weights
from jcomps.training import networks

SATURATION = 0.99
"""|tanh| at or above this is a saturated activation: its gradient 1 − h² is at most 0.02 of a linear unit's."""
SATURATED_SHARE = 0.99
"""A unit is saturated where its activation is saturated on at least this share of the states."""


class States(NamedTuple):
    """The states of one iteration's measured episodes: ``obs`` f32[T, B, obs_size], ``valid`` f32[T, B]."""

    obs: jax.Array
    valid: jax.Array


def empty_states(family, num_envs: int) -> States:
    """Zeros shaped as the states of ``num_envs`` episodes of ``family`` (``rl_loop.iterate``'s ``states``)."""
    T = family.max_steps
    return States(jnp.zeros((T, num_envs, family.obs_size), jnp.float32), jnp.zeros((T, num_envs), jnp.float32))


class PolicyHealth(NamedTuple):
    """The policy a task's RL step starts from and the one it ends with (``TaskMetrics.policy_health``).

    Attributes:
      std_start, std_end: f32[], the exploration std, the mean over action dimensions of exp(log-std).
      entropy_start, entropy_end: f32[], the Gaussian's entropy (nats, summed over action dimensions; the std is
        state-independent, so it is the entropy at every state).
      saturated_start, saturated_end: f32[L], per hidden layer of the mean network, the fraction of its tanh units
        that are saturated (|h| >= ``SATURATION``) on at least ``SATURATED_SHARE`` of the valid states of the task's
        first iteration (start) or last iteration (end).
    """

    std_start: jax.Array
    std_end: jax.Array
    entropy_start: jax.Array
    entropy_end: jax.Array
    saturated_start: jax.Array
    saturated_end: jax.Array


def saturated_fraction(hidden: list, valid: jax.Array) -> jax.Array:
    """f32[L]: per layer of ``hidden`` (activations f32[..., width], leading axes those of ``valid`` f32[...]), the
    fraction of units saturated on at least ``SATURATED_SHARE`` of the valid states (0 without valid states)."""
    w = masked_weights(valid)
    out = []
    for h in hidden:
        share = jnp.tensordot(w, (jnp.abs(h) >= SATURATION).astype(jnp.float32), axes=w.ndim)  # f32[width]
        out.append(jnp.mean((share >= SATURATED_SHARE) & (jnp.sum(valid) > 0)))
    return jnp.stack(out).astype(jnp.float32)


def _std_entropy(policy: dict) -> tuple[jax.Array, jax.Array]:
    log_std = policy["log_std"]
    return jnp.mean(jnp.exp(log_std)), networks.gaussian_entropy(log_std)


def policy_health(policy_fns: networks.PolicyFns, start: dict, end: dict, first: States, last: States
                  ) -> PolicyHealth:
    """The ``PolicyHealth`` of a task that started from policy ``start`` and ended with ``end`` (policies
    ``policy_fns`` applies), their saturation on the states ``first`` and ``last`` of its first and last iteration."""
    start, end, first, last = jax.lax.stop_gradient((start, end, first, last))
    std_start, entropy_start = _std_entropy(start)
    std_end, entropy_end = _std_entropy(end)
    return PolicyHealth(std_start, std_end, entropy_start, entropy_end,
                        saturated_fraction(policy_fns.hidden(start, first.obs), first.valid),
                        saturated_fraction(policy_fns.hidden(end, last.obs), last.valid))
