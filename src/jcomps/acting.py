"""Acting: collect a batch of trajectories with a policy, as a ``lax.scan`` over time of vmapped envs.

Array convention (everywhere in jcomps): trajectories are time-major, ``[T, B, ...]``.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

from jcomps import networks
from jcomps.envs.base import Family


class Trajectory(NamedTuple):
    """A batch of B episodes of T = T_max steps, time-major.

    Attributes:
      obs: f32[T, B, obs_size], observation at which each action was taken.
      action: f32[T, B, A], the action sampled (before the env clips it to [-1, 1]).
      log_prob: f32[T, B], log-probability of ``action`` under the behaviour policy.
      reward: f32[T, B], reward of the transition (0 after termination).
      done: f32[T, B], 1 where this transition terminated the episode (no bootstrap past it).
      valid: f32[T, B], 1 where the step was taken by a live episode (0 after termination).
      success: f32[T, B], the family's per-step success indicator.
      last_obs: f32[B, obs_size], observation after the last step; its value bootstraps the truncation at T.
    """

    obs: jax.Array
    action: jax.Array
    log_prob: jax.Array
    reward: jax.Array
    done: jax.Array
    valid: jax.Array
    success: jax.Array
    last_obs: jax.Array


ActFn = Callable[[Any, jax.Array, jax.Array], tuple[jax.Array, jax.Array]]
"""``act(policy, obs f32[..., obs_size], noise f32[..., A]) -> (action f32[..., A], log_prob f32[...])``: a policy's
action for standard-normal ``noise`` (``networks.action_from_noise`` for the Gaussian policies of the PPO-based
methods; a method with another policy, like PEARL's tanh-Gaussian, brings its own: ``Method.act``)."""


def rollout(family: Family, policy: Any, task, rng: jax.Array, num_envs: int,
            act: ActFn = networks.action_from_noise) -> Trajectory:
    """Runs ``num_envs`` fresh episodes of ``task`` for ``family.max_steps`` steps with ``policy`` (default: a
    Gaussian policy; ``act`` makes the actions of any other kind).

    A family simulated on the host (``family.host_rollout``) runs the whole rollout there when ``act`` has a
    NumPy twin (its ``host_kind``, see ``jcomps.host_acting``); the policy's noise is drawn here either way.
    """
    reset_rng, step_rng = jax.random.split(rng)
    kind = getattr(act, "host_kind", None)
    if family.host_rollout is not None and kind is not None:
        noise = jax.random.normal(step_rng, (family.max_steps, num_envs, family.action_size), jnp.float32)
        obs, action, log_prob, reward, success, last_obs = family.host_rollout(kind, policy, task, noise)
        zeros = jnp.zeros(reward.shape, jnp.float32)  # the host families never terminate (time limits truncate)
        return Trajectory(obs, action, log_prob, reward, zeros, zeros + 1.0, success, last_obs)
    state = jax.vmap(family.reset, (0, None))(jax.random.split(reset_rng, num_envs), task)
    step = jax.vmap(family.step, (0, 0, None))

    def body(state, noise):
        action, log_prob = act(policy, state.obs, noise)
        nxt = step(state, action, task)
        valid = 1.0 - state.done
        done = nxt.done * valid
        return nxt, Trajectory(state.obs, action, log_prob, nxt.reward, done, valid, nxt.success, None)

    noise = jax.random.normal(step_rng, (family.max_steps, num_envs, family.action_size), jnp.float32)
    state, traj = jax.lax.scan(body, state, noise)
    return traj._replace(last_obs=state.obs)
