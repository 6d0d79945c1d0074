"""Acting: collect a batch of trajectories with a policy, as a ``lax.scan`` over time of vmapped envs.

Array convention (everywhere in jcomps): trajectories are time-major, ``[T, B, ...]``.
"""

from __future__ import annotations

import contextlib
import threading
from typing import Any, Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp

from jcomps.envs.base import Family
from jcomps.training import networks


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
action for standard-normal ``noise``, and its log-probability."""


class Actor(NamedTuple):
    """How a method's policies act in a rollout.

    Attributes:
      act: the policy's ``ActFn``.
      host_kind: the name of ``act``'s NumPy twin (``jcomps.envs.host_acting.TWINS``), with which a family simulated on
        the host runs whole rollouts there; None: no twin (such a family is stepped through its ``step``).
    """

    act: ActFn
    host_kind: Optional[str] = None


def actor_of(policy_fns: networks.PolicyFns) -> Actor:
    """The ``Actor`` of a Gaussian policy: ``policy_fns.act`` and its twin."""
    return Actor(policy_fns.act, policy_fns.host_kind)


GAUSSIAN = actor_of(networks.GAUSSIAN)
"""The Gaussian MLP policy's ``Actor`` (the PPO-based methods'; PEARL's tanh-Gaussian has its own)."""


_ACTIVE = threading.local()  # .stack: the traced conditions of the enclosing only_if contexts (per tracing thread)


def _active_stack() -> list:
    if not hasattr(_ACTIVE, "stack"):
        _ACTIVE.stack = []
    return _ACTIVE.stack


@contextlib.contextmanager
def only_if(active: jax.Array):
    """Rollouts traced inside are needed only where ``active`` (a traced bool scalar) is True: elsewhere the
    caller discards them. ``rl_loop.iterate`` sets it to its loop condition: a batched (vmapped) while loop runs its
    body for every member until all have stopped and throws away the stopped members' results, so a family
    simulated on the host (``Family.host_rollout``) skips their episodes. Nested uses combine (and)."""
    stack = _active_stack()
    stack.append(active if not stack else stack[-1] & active)
    try:
        yield
    finally:
        stack.pop()


def rollout(family: Family, policy: Any, task, rng: jax.Array, num_envs: int, actor: Actor = GAUSSIAN) -> Trajectory:
    """Runs ``num_envs`` fresh episodes of ``task`` for ``family.max_steps`` steps with ``policy``, acting by
    ``actor`` (default: the Gaussian MLP policy's).

    A family simulated on the host (``family.host_rollout``) runs the whole rollout there when the actor has a
    NumPy twin (``actor.host_kind``, see ``jcomps.envs.host_acting``); the policy's noise is drawn here either way.
    Inside ``only_if(active)`` the host skips the rollout where ``active`` is False and returns zeros.
    """
    reset_rng, step_rng = jax.random.split(rng)
    if family.host_rollout is not None and actor.host_kind is not None:
        noise = jax.random.normal(step_rng, (family.max_steps, num_envs, family.action_size), jnp.float32)
        stack = _active_stack()
        active = stack[-1] if stack else jnp.array(True)
        obs, action, log_prob, reward, success, last_obs = family.host_rollout(actor.host_kind, policy, task, noise,
                                                                               active)
        zeros = jnp.zeros(reward.shape, jnp.float32)  # the host families never terminate (time limits truncate)
        return Trajectory(obs, action, log_prob, reward, zeros, zeros + 1.0, success, last_obs)
    state = jax.vmap(family.reset, (0, None))(jax.random.split(reset_rng, num_envs), task)
    step = jax.vmap(family.step, (0, 0, None))

    def body(state, noise):
        action, log_prob = actor.act(policy, state.obs, noise)
        nxt = step(state, action, task)
        valid = 1.0 - state.done
        done = nxt.done * valid
        return nxt, Trajectory(state.obs, action, log_prob, nxt.reward, done, valid, nxt.success, None)

    noise = jax.random.normal(step_rng, (family.max_steps, num_envs, family.action_size), jnp.float32)
    state, traj = jax.lax.scan(body, state, noise)
    return traj._replace(last_obs=state.obs)
