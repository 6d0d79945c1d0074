"""The meta step M of CoMPS (paper Algorithm 1): off-policy inner policy gradient, behaviour-cloning outer loss.

For every seen task j (a slot of ``buffers.SequenceStores`` with ``task_valid``):

- inner: φ_j = θ + α ∇_θ J_j(θ), J_j(θ) = (1/N) Σ ρ_i log π_θ(a_i|s_i) Â_i on m trajectories of D_j, with
  clipped importance weights ρ_i and V-trace advantages Â from value head j (both constants: no gradient);
- outer: L_BC(φ_j) = −mean log π_{φ_j}(a|s) on a minibatch of D*_j;
- θ ← Adam(θ, ∇_θ mean_j L_BC(φ_j)), the gradient flowing *through* the inner step (second order) unless
  ``first_order``. The value heads learn V-trace targets by l2 at every outer step.

Masked slots (tasks not seen yet) contribute nothing, so one compiled step serves every prefix of a sequence.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax

from jcomps import buffers, networks, vtrace
from jcomps.ppo import all_finite, check_field, masked_mean


@dataclasses.dataclass(frozen=True)
class MetaConfig:
    """Hyperparameters of the meta step (paper defaults where the paper gives them)."""

    outer_learning_rate: float = 0.005
    """Adam learning rate of the outer (imitation) update (paper: 0.005)."""
    inner_learning_rate: float = 0.005
    """α, the inner policy-gradient step size (paper: 0.005 Ant and Cheetah, 0.0025 MetaWorld)."""
    num_meta_steps: int = 25
    """Meta training steps after each task (paper: 25)."""
    num_outer_steps: int = 5
    """Outer imitation steps per meta step (paper: 5)."""
    inner_trajectories: int = 10
    """m, trajectories of D_j per inner step."""
    skilled_trajectories: int = 10
    """Trajectories of D*_j per outer minibatch."""
    value_learning_rate: float = 1e-3
    """Adam learning rate of the per-task value heads."""
    discount: float = 0.99
    """γ of the V-trace targets."""
    rho_bar: float = 1.0
    """ρ̄, importance-weight clip in the V-trace targets."""
    c_bar: float = 1.0
    """c̄, trace-coefficient clip in the V-trace targets."""
    pg_rho_bar: float = 1.0
    """Importance-weight clip in the inner policy gradient."""
    importance_sampling: bool = True
    """Weight the inner policy gradient and the V-trace targets by π_θ/μ (off for GMPS+PPO)."""
    vtrace_baseline: bool = True
    """Baseline the inner gradient with V-trace targets; off: on-policy returns minus V (GMPS+PPO)."""
    first_order: bool = False
    """Stop the gradient through the inner step (first-order approximation)."""

    def __post_init__(self):
        for name in ("outer_learning_rate", "inner_learning_rate", "value_learning_rate", "rho_bar", "c_bar",
                     "pg_rho_bar"):
            check_field(getattr(self, name) > 0, name, getattr(self, name), "a number > 0")
        for name in ("num_meta_steps", "num_outer_steps"):
            check_field(getattr(self, name) >= 0, name, getattr(self, name), "an integer >= 0")
        for name in ("inner_trajectories", "skilled_trajectories"):
            check_field(getattr(self, name) >= 1, name, getattr(self, name), "an integer >= 1")
        check_field(0 < self.discount <= 1, "discount", self.discount, "a number in (0, 1]")


class TaskBatch(NamedTuple):
    """One task's samples for a meta step: ``off`` from D_j ([T, m, ...] + mask [m]), ``skilled`` from D*_j."""

    off: buffers.OffPolicyStore
    skilled_obs: jax.Array
    skilled_action: jax.Array
    skilled_valid: jax.Array


def init_value_heads(rng, obs_size: int, hidden_sizes, num_slots: int) -> list:
    """A value MLP with one output per task slot."""
    return networks.mlp_init(rng, (obs_size, *hidden_sizes, num_slots))


def _head(value, obs, slot):
    return jnp.take(networks.mlp_apply(value, obs), slot, axis=-1)


def inner_targets(config: MetaConfig, policy, value, slot, off: buffers.OffPolicyStore):
    """(advantages f32[T, m] including clipped ρ, V-trace value targets f32[T, m]) for the inner step."""
    traj = off.traj
    values = _head(value, traj.obs, slot)
    bootstrap = _head(value, traj.last_obs, slot)
    discounts = config.discount * (1.0 - traj.done)
    if config.importance_sampling:
        log_rhos = networks.policy_log_prob(policy, traj.obs, traj.action) - traj.log_prob
    else:
        log_rhos = jnp.zeros_like(traj.log_prob)
    out = vtrace.vtrace(values, bootstrap, traj.reward, discounts, log_rhos, rho_bar=config.rho_bar,
                        c_bar=config.c_bar, pg_rho_bar=config.pg_rho_bar)
    if config.vtrace_baseline:
        return out.pg_advantages, out.vs
    on_policy = vtrace.vtrace(values, bootstrap, traj.reward, discounts, jnp.zeros_like(log_rhos))
    returns = on_policy.vs
    return jax.lax.stop_gradient(returns - values), returns


def adapt(config: MetaConfig, policy, off: buffers.OffPolicyStore, advantages):
    """φ = θ + α ∇_θ J(θ) with J the importance-weighted policy-gradient objective on ``off``."""
    mask = off.traj.valid * off.mask[None, :]

    def objective(p):
        return masked_mean(networks.policy_log_prob(p, off.traj.obs, off.traj.action) * advantages, mask)

    grads = jax.grad(objective)(policy)
    if config.first_order:
        grads = jax.lax.stop_gradient(grads)
    return jax.tree.map(lambda p, g: p + config.inner_learning_rate * g, policy, grads)


def bc_loss(policy, obs, action, valid):
    """Behaviour cloning: −mean log π(a|s) over valid samples."""
    return -masked_mean(networks.policy_log_prob(policy, obs, action), valid)


def task_loss(config: MetaConfig, policy, value, slot, batch: TaskBatch):
    """L_BC(φ_j) for one task, with φ_j adapted from ``policy`` on the task's off-policy batch."""
    advantages, _ = inner_targets(config, policy, value, slot, batch.off)
    adapted = adapt(config, policy, batch.off, advantages)
    return bc_loss(adapted, batch.skilled_obs, batch.skilled_action, batch.skilled_valid)


def _zero_unseen(batches: TaskBatch, task_valid) -> TaskBatch:
    """Zeros every unseen slot's data, so that whatever it holds (even NaN) cannot reach a gradient."""
    def zero(x):
        keep = task_valid.reshape(task_valid.shape + (1,) * (x.ndim - 1))
        return jnp.where(keep, x, jnp.zeros_like(x))

    return jax.tree.map(zero, batches)


def meta_loss(config: MetaConfig, policy, value, batches: TaskBatch, task_valid):
    """Mean over valid task slots of ``task_loss``; ``batches`` has a leading [num_slots] axis."""
    batches = _zero_unseen(batches, task_valid)
    slots = jnp.arange(task_valid.shape[0])
    losses = jax.vmap(lambda s, b: task_loss(config, policy, value, s, b))(slots, batches)
    return masked_mean(jnp.where(task_valid, losses, 0.0), task_valid.astype(jnp.float32))


def value_loss(config: MetaConfig, policy, value, batches: TaskBatch, task_valid):
    """l2 of every valid head against its V-trace targets (targets are constants)."""
    def one(slot, b):
        _, targets = inner_targets(config, policy, value, slot, b.off)
        err = jnp.square(_head(value, b.off.traj.obs, slot) - targets)
        return masked_mean(err, b.off.traj.valid * b.off.mask[None, :])

    losses = jax.vmap(one)(jnp.arange(task_valid.shape[0]), _zero_unseen(batches, task_valid))
    return masked_mean(jnp.where(task_valid, losses, 0.0), task_valid.astype(jnp.float32))


def sample_batches(config: MetaConfig, stores: buffers.SequenceStores, rng) -> TaskBatch:
    """Samples each slot's inner (D_j) and outer (D*_j) trajectories; leading axis [num_slots]."""
    def one(key, skilled: buffers.SkilledStore, off: buffers.OffPolicyStore):
        k1, k2 = jax.random.split(key)
        idx, ok = buffers.pick_rows(k1, off.mask > 0, config.inner_trajectories)
        per_step = off.traj._replace(last_obs=None)
        traj = jax.tree.map(lambda x: jnp.take(x, idx, axis=1), per_step)._replace(last_obs=off.traj.last_obs[idx])
        sidx, sok = buffers.pick_rows(k2, jnp.isfinite(skilled.returns), config.skilled_trajectories)
        return TaskBatch(buffers.OffPolicyStore(traj, ok), jnp.take(skilled.obs, sidx, axis=1),
                         jnp.take(skilled.action, sidx, axis=1), jnp.take(skilled.valid, sidx, axis=1) * sok)

    num_slots = stores.task_valid.shape[0]
    return jax.vmap(one)(jax.random.split(rng, num_slots), stores.skilled, stores.offpolicy)


class MetaState(NamedTuple):
    """policy, value heads and their Adam states."""

    policy: dict
    value: list
    policy_opt: optax.OptState
    value_opt: optax.OptState


def optimizers(config: MetaConfig):
    """(outer policy optimiser, value optimiser)."""
    return optax.adam(config.outer_learning_rate), optax.adam(config.value_learning_rate)


def meta_train(config: MetaConfig, state: MetaState, stores: buffers.SequenceStores, rng):
    """``num_meta_steps`` × ``num_outer_steps`` outer updates; returns (state, outer losses f32[steps])."""
    policy_opt, value_opt = optimizers(config)

    def outer(state: MetaState, key):
        batches = sample_batches(config, stores, key)
        loss, g = jax.value_and_grad(meta_loss, argnums=1)(config, state.policy, state.value, batches,
                                                             stores.task_valid)
        vg = jax.grad(value_loss, argnums=2)(config, state.policy, state.value, batches, stores.task_valid)
        finite = all_finite((loss, g, vg))
        up, popt = policy_opt.update(g, state.policy_opt, state.policy)
        vup, vopt = value_opt.update(vg, state.value_opt, state.value)
        new = MetaState(optax.apply_updates(state.policy, up), optax.apply_updates(state.value, vup), popt, vopt)
        new = jax.tree.map(lambda a, b: jnp.where(finite, a, b), new, state)
        return new, jnp.where(finite, loss, jnp.nan)

    steps = config.num_meta_steps * config.num_outer_steps
    return jax.lax.scan(outer, state, jax.random.split(rng, steps))
