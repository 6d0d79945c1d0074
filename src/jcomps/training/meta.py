"""The meta step M of CoMPS (paper Algorithm 1): off-policy inner policy gradient, behaviour-cloning outer loss.

For every seen task j (a slot of ``buffers.SequenceStores`` with ``task_valid``):

- inner: φ_j = θ + α ∇_θ J_j(θ), J_j(θ) = (1/N) Σ ρ_i log π_θ(a_i|s_i) Â_i on m trajectories of D_j, with
  clipped importance weights ρ_i and V-trace advantages Â from value head j (both constants: no gradient);
- outer: L_BC(φ_j) = −mean log π_{φ_j}(a|s) on a minibatch of D*_j (or the mean action's squared error,
  ``outer_loss``); L_BC(θ) − L_BC(φ_j), what the inner step gains, is reported (``SlotStats.inner_gain``);
- θ ← Adam(θ, ∇_θ mean_j L_BC(φ_j)), the gradient flowing *through* the inner step (second order) unless
  ``first_order``. The value heads (one value MLP per task slot) learn V-trace targets by l2 at every outer step,
  in the RL step's reward units (``reward_scale``); a new task's head starts from the RL step's trained value
  function (``value_init``).

Masked slots (tasks not seen yet) contribute nothing, so one compiled step serves every prefix of a sequence.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar, NamedTuple, Optional

import jax
import jax.numpy as jnp
import optax

from jcomps import progress
from jcomps.numerics import (
    all_finite, check_field, check_finite_fields, guarded_update, holds_tracers, keep_if_finite,
    masked_explained_variance, masked_mean, masked_standardize, masked_var, optimizer_step,
)
from jcomps.progress import ProgressFn
from jcomps.training import buffers, networks, vtrace


@dataclasses.dataclass(frozen=True)
class MetaConfig:
    """Hyperparameters of the meta step (paper defaults where the paper gives them)."""

    outer_learning_rate: float = 0.005
    """Adam learning rate of the outer (imitation) update (paper: 0.005)."""
    inner_learning_rate: float = 0.005
    """α, the inner policy-gradient step size (paper: 0.005 Ant and Cheetah, 0.0025 MetaWorld); 0: no inner step
    (φ_j = θ: the meta step is multi-task behaviour cloning, whose inner-step gain is 0)."""
    inner_step_sizes: str = "fixed"
    """The inner step's size: ``fixed``, the one α ``inner_learning_rate`` for every parameter (the paper); ``learnt``,
    one step size per policy parameter, kept in the policy (``policy["inner_lr"]``, ``with_inner_step_sizes``),
    initialised at ``inner_learning_rate`` and meta-learnt with θ by the outer loss (Meta-SGD, Li et al. 2017: the
    authors' prototype's policy, ``maml_minimal_gauss_mlp_policy_adaptivestep_ppo``). Updates other than the meta
    step's outer one leave them unchanged: no other loss reads them."""
    num_meta_steps: int = 25
    """Meta training steps after each task (paper: 25)."""
    num_outer_steps: int = 5
    """Outer imitation steps per meta step (paper: 5)."""
    inner_trajectories: int = 10
    """m, trajectories of D_j per inner step."""
    skilled_trajectories: int = 10
    """Trajectories of D*_j per outer minibatch."""
    value_learning_rate: Optional[float] = None
    """Adam learning rate of the per-task value heads in the meta step; None: the RL step's learning rate (the rate
    its critic, which a new head copies, was trained at; CoMPS resolves it), 1e-3 where there is no RL step."""
    discount: float = 0.99
    """γ of the V-trace targets."""
    rho_bar: float = 1.0
    """ρ̄, importance-weight clip in the V-trace targets."""
    c_bar: float = 1.0
    """c̄, trace-coefficient clip in the V-trace targets."""
    pg_rho_bar: float = 1.0
    """Importance-weight clip in the inner policy gradient."""
    inner_ratio_clip: float = 0.0
    """ε of the authors' PPO-based inner step (their GMPS+PPO, ``use_ppo``): without importance sampling the inner
    policy gradient is weighted by π_θ/μ clipped to [1 − ε, 1 + ε] (a constant weight, 0.2 in their code); 0: off,
    every weight 1. Only without ``importance_sampling``."""
    importance_sampling: bool = True
    """Weight the inner policy gradient and the V-trace targets by π_θ/μ (off for GMPS+PPO)."""
    vtrace_baseline: bool = True
    """Baseline the inner gradient with V-trace targets; off: on-policy returns minus V (GMPS+PPO)."""
    first_order: bool = False
    """Stop the gradient through the inner step (first-order approximation)."""
    normalize_advantages: bool = False
    """Standardise the inner advantages per task (zero mean, unit std over its valid samples) before the
    importance weights, as GMPS's code does (``center_adv``); off: the raw advantages (docs/design.md)."""
    task_chunk: int = 0
    """Task slots computed in parallel per loop iteration of the meta step; 0: 1 on CPU, 8 on accelerators."""
    reward_scale: Optional[float] = None
    """Rewards are multiplied by this in the V-trace targets and inner advantages; None: the RL step's
    ``reward_scale`` (the units its value function learnt; CoMPS resolves it), 1.0 where there is no RL step."""
    value_init: str = "rl_step"
    """How a new task's value head starts: ``rl_step``, a copy of the RL step's trained value function (fitted to
    the very data D_i holds); ``random``, its random initialisation (an ablation: the head then
    starts far from the returns it must fit)."""
    value_fit_steps: int = 200
    """Full-batch Adam steps (``value_fit_learning_rate``, a fresh Adam state) that fit a new task's head to the
    discounted returns of D_i before its first meta step (on-policy V-trace targets: the behaviour policy's own
    returns, bootstrapped by the head at the time limit); 0: none (an ablation)."""
    value_fit_learning_rate: float = 1e-3
    """Adam learning rate of that fit."""
    optimizer_state: str = "reset"
    """The meta step's Adam states (policy and value heads) at the start of a meta phase: ``reset``, fresh for every
    meta phase (the moments of the last phase belong to another θ: the warm start jumps it); ``carry``, as the last
    meta phase left them (docs/log.md, "The ablation ladder: one feature per rung", has both
    measured)."""
    outer_loss: str = "nll"
    """The outer (imitation) loss on D*_j: ``nll``, −mean log π_φ(a|s), the Gaussian negative log-likelihood with the
    learned std (the paper's Eq. 1: the meta step also sets the next task's exploration std); ``mean_mse``, the mean
    squared error of the policy's mean action (averaged over action dimensions), the std kept out of the meta step
    (its outer gradient is zero, so θ's std stays where the meta phase started), as the authors' code cloned
    (docs/results.md, "The ladder as the paper's authors ran it", has both measured)."""
    hold_std: Optional[bool] = None
    """Keep the policy's std out of the meta step: no inner or outer gradient reaches it, so θ's std stays where
    the meta phase started; None: held where the RL step's std is fixed (its ``std_mode``; CoMPS resolves it), not
    held where there is no RL step. ``outer_loss="mean_mse"`` holds it either way."""
    outer_update: str = "mean"
    """How θ is updated: ``mean``, one Adam step on the mean over seen tasks per outer step; ``sequential``,
    Algorithm 1 read literally: per meta step, task after task (newest last), ``num_outer_steps`` Adam steps on
    that task alone. Both make the same number of per-task gradient evaluations (docs/design.md)."""

    SETTINGS_PART: ClassVar[str] = "meta"
    """Which of a family's calibrated settings apply to this config (``jcomps.envs.settings``)."""
    TRACED: ClassVar[frozenset] = frozenset({
        "outer_learning_rate", "inner_learning_rate", "value_learning_rate", "value_fit_learning_rate", "discount",
        "rho_bar", "c_bar", "pg_rho_bar", "reward_scale"})
    """Fields that may hold traced scalars (a hyperparameter-grid axis inside one compiled program)."""

    def __post_init__(self):
        if holds_tracers(self):  # a traced grid value (``numerics.holds_tracers``)
            return
        check_finite_fields(self)
        for name in ("outer_learning_rate", "value_fit_learning_rate", "rho_bar", "c_bar", "pg_rho_bar"):
            check_field(getattr(self, name) > 0, name, getattr(self, name), "a number > 0")
        check_field(self.inner_learning_rate >= 0, "inner_learning_rate", self.inner_learning_rate,
                    "a number >= 0 (0: no inner step, the meta step is multi-task behaviour cloning)")
        check_field(self.value_learning_rate is None or self.value_learning_rate > 0, "value_learning_rate",
                    self.value_learning_rate, "None (the RL step's) or a number > 0")
        for name in ("num_meta_steps", "num_outer_steps", "value_fit_steps"):
            check_field(getattr(self, name) >= 0, name, getattr(self, name), "an integer >= 0")
        check_field(self.task_chunk >= 0, "task_chunk", self.task_chunk, "an integer >= 0 (0: by backend)")
        for name in ("inner_trajectories", "skilled_trajectories"):
            check_field(getattr(self, name) >= 1, name, getattr(self, name), "an integer >= 1")
        check_field(0 < self.discount <= 1, "discount", self.discount, "a number in (0, 1]")
        check_field(0 <= self.inner_ratio_clip < 1, "inner_ratio_clip", self.inner_ratio_clip, "a number in [0, 1)")
        check_field(self.inner_ratio_clip == 0 or not self.importance_sampling, "inner_ratio_clip",
                    self.inner_ratio_clip, "0 with importance_sampling (the clip is the unweighted rungs' option)")
        check_field(self.outer_loss in OUTER_LOSSES, "outer_loss", self.outer_loss, ", ".join(OUTER_LOSSES))
        check_field(self.inner_step_sizes in INNER_STEP_SIZES, "inner_step_sizes", self.inner_step_sizes,
                    ", ".join(INNER_STEP_SIZES))
        check_field(self.outer_update in OUTER_UPDATES, "outer_update", self.outer_update, ", ".join(OUTER_UPDATES))
        check_field(self.reward_scale is None or self.reward_scale > 0, "reward_scale", self.reward_scale,
                    "None (the RL step's) or a number > 0")
        check_field(self.value_init in VALUE_INITS, "value_init", self.value_init, ", ".join(VALUE_INITS))
        check_field(self.optimizer_state in OPTIMIZER_STATES, "optimizer_state", self.optimizer_state,
                    ", ".join(OPTIMIZER_STATES))


OUTER_UPDATES = ("mean", "sequential")
INNER_STEP_SIZES = ("fixed", "learnt")
OUTER_LOSSES = ("nll", "mean_mse")
VALUE_INITS = ("rl_step", "random")
OPTIMIZER_STATES = ("carry", "reset")

class TaskBatch(NamedTuple):
    """One task's samples for a meta step: ``off`` from D_j ([T, m, ...] + mask [m]), ``skilled`` from D*_j."""

    off: buffers.OffPolicyStore
    skilled_obs: jax.Array
    skilled_action: jax.Array
    skilled_valid: jax.Array


class SlotStats(NamedTuple):
    """The health of the meta step on one task slot (or a mean over the seen slots); every field f32.

    Attributes:
      bc_loss: L_BC(φ_j), the imitation loss of the adapted policy on D*_j.
      value_l2: mean (V_j − v_s)² against the V-trace targets v_s (the heads' loss).
      value_ev: explained variance of V_j against the discounted returns G of D_j's data, 1 − Var(G − V)/Var(G):
        the fit to V-trace targets alone can look perfect while the targets follow a wrong head.
      value_ev_targets: explained variance of V_j against the V-trace targets.
      value_bias: mean (V_j − G).
      return_std: standard deviation of G (the spread to judge ``value_bias`` against).
      adv_abs: mean |Â| of the inner step's advantages (importance weights included).
      rho: mean clipped importance weight of the inner step, min(ρ̄_pg, π_θ/μ): how much the old task still
        contributes (1 without importance sampling).
      inner_gain: L_BC(θ) − L_BC(φ_j) on the same D*_j samples: how much the one inner step helps task j (0 with
        α = 0; negative where it hurts).
    """

    bc_loss: jax.Array
    value_l2: jax.Array
    value_ev: jax.Array
    value_ev_targets: jax.Array
    value_bias: jax.Array
    return_std: jax.Array
    adv_abs: jax.Array
    rho: jax.Array
    inner_gain: jax.Array


def init_value_heads(rng, obs_size: int, hidden_sizes, num_slots: int) -> list:
    """One value MLP (``hidden_sizes``, one output, as the RL step's value function) per task slot, stacked on a
    leading [num_slots] axis. Initialised one slot at a time (``lax.map``): a batched QR in the orthogonal
    initialiser can deadlock XLA:CPU's pool on several host devices (``continual.init_seeds``)."""
    return jax.lax.map(lambda k: networks.mlp_init(k, (obs_size, *hidden_sizes, 1)), jax.random.split(rng, num_slots))


def head_params(value, slot) -> list:
    """Head ``slot``'s MLP layers out of the stacked heads."""
    return jax.tree.map(lambda x: jax.lax.dynamic_index_in_dim(x, slot, keepdims=False), value)


def set_head(value, slot, layers) -> list:
    """The stacked heads with head ``slot`` replaced by ``layers`` (an MLP of the same shapes, e.g. the RL step's
    value function)."""
    return jax.tree.map(lambda x, y: jax.lax.dynamic_update_index_in_dim(x, y.astype(x.dtype), slot, 0), value,
                        layers)


def _head(value, obs, slot):
    """V_slot(obs)."""
    return networks.value_apply(head_params(value, slot), obs)


def _reward_scale(config: MetaConfig):
    return 1.0 if config.reward_scale is None else config.reward_scale


def _rewards_and_discounts(config: MetaConfig, traj):
    """(rewards × ``reward_scale``, per-step discounts γ·(1 − done)), f32[T, m]: what every target here is made of."""
    return traj.reward * _reward_scale(config), config.discount * (1.0 - traj.done)


def _vtrace_terms(config: MetaConfig, log_prob, values, bootstrap, off: buffers.OffPolicyStore):
    """(inner advantages f32[T, m] including clipped ρ, value targets f32[T, m], clipped ρ of the inner step
    f32[T, m]); constants (no gradient). Rewards are scaled by ``reward_scale``.

    With ``normalize_advantages`` the advantages are standardised over the task's valid samples before the
    importance weights multiply them (GMPS's ``center_adv``).
    """
    traj = off.traj
    reward, discounts = _rewards_and_discounts(config, traj)
    log_ratio = log_prob - traj.log_prob
    log_rhos = log_ratio if config.importance_sampling else jnp.zeros_like(traj.log_prob)
    values, bootstrap, log_rhos, log_ratio = jax.lax.stop_gradient((values, bootstrap, log_rhos, log_ratio))
    if config.vtrace_baseline:
        out = vtrace.vtrace(values, bootstrap, reward, discounts, log_rhos, rho_bar=config.rho_bar,
                            c_bar=config.c_bar, pg_rho_bar=config.pg_rho_bar)
        weights, targets = out.clipped_pg_rhos, out.vs
        if not config.normalize_advantages:
            return out.pg_advantages, out.vs, weights
        raw = reward + discounts * jnp.concatenate([out.vs[1:], bootstrap[None]], axis=0) - values
    else:
        # No V-trace: the advantage is the bootstrapped discounted return minus V; importance weights (if on)
        # still weight the step.
        targets = vtrace.discounted_returns(reward, discounts, bootstrap)
        if config.importance_sampling:
            weights = jnp.minimum(jnp.exp(log_rhos), config.pg_rho_bar)
        elif config.inner_ratio_clip > 0:  # the authors' PPO-based inner step: the ratio clipped to [1 − ε, 1 + ε]
            weights = jnp.clip(jnp.exp(log_ratio), 1.0 - config.inner_ratio_clip, 1.0 + config.inner_ratio_clip)
        else:
            weights = jnp.ones_like(log_rhos)
        raw = targets - values
    if config.normalize_advantages:
        raw = masked_standardize(raw, traj.valid * off.mask[None, :])
    return weights * raw, targets, weights


def adapt(config: MetaConfig, policy, off: buffers.OffPolicyStore, advantages, log_prob_vjp):
    """φ = θ + α ∇_θ J(θ) with J the importance-weighted policy-gradient objective on ``off``.

    ``log_prob_vjp``: the VJP of θ ↦ log π_θ(a|s) on ``off`` (the caller has run that forward pass already).
    """
    mask = off.traj.valid * off.mask[None, :]
    # ∇_θ masked_mean(log π_θ · Â) is the VJP of log π_θ with cotangent Â·mask / Σmask.
    (grads,) = log_prob_vjp(advantages * mask / jnp.maximum(jnp.sum(mask), 1.0))
    if config.first_order:
        grads = jax.lax.stop_gradient(grads)
    sizes = policy.get("inner_lr")
    if sizes is None:
        return jax.tree.map(lambda p, g: p + config.inner_learning_rate * g, policy, grads)
    # Meta-SGD: each parameter steps by its own (meta-learnt) size.
    return {**policy, **{k: jax.tree.map(lambda p, a, g: p + a * g, policy[k], sizes[k], grads[k]) for k in sizes}}


STEPPED = ("mean", "log_std")
"""The entries of a policy that the inner step moves and that have learnt step sizes (not its statistics)."""


def with_inner_step_sizes(config: MetaConfig, policy: dict) -> dict:
    """``policy`` with one inner step size per parameter of its ``STEPPED`` entries, all at
    ``config.inner_learning_rate`` (``policy["inner_lr"]``), where ``inner_step_sizes`` is ``learnt`` and it has none
    yet; else ``policy`` unchanged."""
    if config.inner_step_sizes != "learnt" or "inner_lr" in policy:
        return policy
    alpha = jnp.asarray(config.inner_learning_rate, jnp.float32)
    return {**policy, "inner_lr": {k: jax.tree.map(lambda x: jnp.full(x.shape, alpha, jnp.float32), policy[k])
                                   for k in STEPPED}}


def bc_loss(policy, obs, action, valid):
    """Behaviour cloning: −mean log π(a|s) over valid samples."""
    return -masked_mean(networks.GAUSSIAN.log_prob(policy, obs, action), valid)


def mean_mse_loss(policy, obs, action, valid):
    """Behaviour cloning of the mean: the mean over valid samples and action dimensions of (μ_θ(s) − a)², the std
    left out (the authors' code: ``reduce_mean(m**2 - 2*m*a_star + a_star**2)``)."""
    mean, _ = networks.GAUSSIAN.dist(policy, obs)
    return masked_mean(jnp.mean(jnp.square(mean - action), axis=-1), valid)


def outer_loss(config: MetaConfig, policy, obs, action, valid):
    """The outer loss ``config.outer_loss`` of ``policy`` on skilled samples (``bc_loss`` or ``mean_mse_loss``)."""
    return (mean_mse_loss if config.outer_loss == "mean_mse" else bc_loss)(policy, obs, action, valid)


def fit_head(config: MetaConfig, policy, value, slot, off: buffers.OffPolicyStore):
    """The stacked heads with head ``slot`` fitted by ``value_fit_steps`` full-batch Adam steps (a fresh Adam
    state, ``value_fit_learning_rate``) to the discounted returns of ``off`` (one task's D, collected by the behaviour
    policy, so V-trace's targets with ρ = 1: the returns), bootstrapped by the head at the time limit and
    recomputed at every step; observations normalised by ``policy``'s statistics, as in the meta step."""
    if config.value_fit_steps == 0:
        return value
    traj = off.traj
    mask = traj.valid * off.mask[None, :]
    obs, last_obs = networks.normalize_obs(policy, traj.obs), networks.normalize_obs(policy, traj.last_obs)
    reward, discounts = _rewards_and_discounts(config, traj)
    optimizer = optax.adam(config.value_fit_learning_rate)

    def loss(head):
        bootstrap = jax.lax.stop_gradient(networks.value_apply(head, last_obs))
        returns = vtrace.discounted_returns(reward, discounts, bootstrap)
        return masked_mean(jnp.square(networks.value_apply(head, obs) - returns), mask)

    def step(_, carry):
        head, opt = carry
        head, opt, _ = guarded_update(optimizer, jax.grad(loss)(head), opt, head)
        return head, opt

    head = head_params(value, slot)
    head, _ = jax.lax.fori_loop(0, config.value_fit_steps, step, (head, optimizer.init(head)))
    return set_head(value, slot, head)


def _stats(config: MetaConfig, bc, value_l2, values, bootstrap, targets, advantages, weights, bc_theta,
           off: buffers.OffPolicyStore):
    """SlotStats of one slot's batch (``bc`` and ``value_l2`` as given, the rest constants; ``bc_theta`` the outer
    loss of the unadapted policy on the same samples)."""
    values, bootstrap, targets, advantages, weights, bc_theta = jax.lax.stop_gradient(
        (values, bootstrap, targets, advantages, weights, bc_theta))
    traj = off.traj
    mask = traj.valid * off.mask[None, :]
    returns = vtrace.discounted_returns(*_rewards_and_discounts(config, traj), bootstrap)
    return SlotStats(
        bc_loss=bc,
        value_l2=value_l2,
        value_ev=masked_explained_variance(returns, values, mask),
        value_ev_targets=masked_explained_variance(targets, values, mask),
        value_bias=masked_mean(values - returns, mask),
        return_std=jnp.sqrt(masked_var(returns, mask)),
        adv_abs=masked_mean(jnp.abs(advantages), mask),
        rho=masked_mean(weights, mask),
        inner_gain=bc_theta - jax.lax.stop_gradient(bc))


def head_objective(config: MetaConfig, policy, head, batch: TaskBatch):
    """``slot_objective`` with the slot's value head ``head`` (its MLP layers) given directly: its gradient in
    ``head`` is that head's slice of the stacked heads' gradient."""
    off = batch.off
    # With the std kept out of the meta step, neither the outer gradient nor the inner step reaches it.
    hold = networks.held_std if config.outer_loss == "mean_mse" or config.hold_std else (lambda p: p)
    policy = hold(policy)
    # The value heads see observations normalised like the policy's (statistics are constants).
    values = networks.value_apply(head, networks.normalize_obs(policy, off.traj.obs))
    bootstrap = networks.value_apply(head, networks.normalize_obs(policy, off.traj.last_obs))
    log_prob, log_prob_vjp = jax.vjp(lambda p: networks.GAUSSIAN.log_prob(hold(p), off.traj.obs, off.traj.action),
                                     policy)
    advantages, targets, weights = _vtrace_terms(config, log_prob, values, bootstrap, off)
    adapted = adapt(config, policy, off, advantages, log_prob_vjp)
    bc = outer_loss(config, adapted, batch.skilled_obs, batch.skilled_action, batch.skilled_valid)
    bc_theta = outer_loss(config, policy, batch.skilled_obs, batch.skilled_action, batch.skilled_valid)
    value_l2 = masked_mean(jnp.square(values - targets), off.traj.valid * off.mask[None, :])
    return bc + value_l2, _stats(config, bc, value_l2, values, bootstrap, targets, advantages, weights, bc_theta,
                                 off)


def slot_objective(config: MetaConfig, policy, value, slot, batch: TaskBatch):
    """L_BC(φ_slot) + the value head's l2, and SlotStats as aux, for one task slot.

    Its gradient in ``policy`` is the task's meta-gradient (through the inner step unless ``first_order``); in
    ``value`` it is the l2 gradient of head ``slot`` (V-trace targets and advantages are constants), so one
    backward pass serves both. The forward passes of the policy and the value head on D_j are shared between the
    importance weights, the targets, the inner objective and the value loss.
    """
    return head_objective(config, policy, head_params(value, slot), batch)


def task_loss(config: MetaConfig, policy, value, slot, batch: TaskBatch):
    """L_BC(φ_j) for one task, with φ_j adapted from ``policy`` on the task's off-policy batch."""
    return slot_objective(config, policy, value, slot, batch)[1].bc_loss


def _zero_unseen(batches, task_valid):
    """Zeros every unseen slot of a pytree with a leading slot axis (data, or per-slot gradients), with
    ``where``, so that whatever an unseen slot holds (even NaN) cannot reach a gradient or a sum."""
    def zero(x):
        keep = task_valid.reshape(task_valid.shape + (1,) * (x.ndim - 1))
        return jnp.where(keep, x, jnp.zeros_like(x))

    return jax.tree.map(zero, batches)


def meta_loss(config: MetaConfig, policy, value, batches: TaskBatch, task_valid):
    """Mean over valid task slots of ``task_loss``; ``batches`` has a leading [num_slots] axis.

    The reference form of the meta objective (all slots at once); ``meta_gradients`` computes its gradient slot
    by slot for speed.
    """
    batches = _zero_unseen(batches, task_valid)
    slots = jnp.arange(task_valid.shape[0])
    losses = jax.vmap(lambda s, b: task_loss(config, policy, value, s, b))(slots, batches)
    return masked_mean(jnp.where(task_valid, losses, 0.0), task_valid.astype(jnp.float32))


def _sample_slot(config: MetaConfig, key, skilled: buffers.SkilledStore, off: buffers.OffPolicyStore) -> TaskBatch:
    k1, k2 = jax.random.split(key)
    idx, ok = buffers.pick_rows(k1, off.mask > 0, config.inner_trajectories)
    per_step = off.traj._replace(last_obs=None)
    traj = jax.tree.map(lambda x: jnp.take(x, idx, axis=1), per_step)._replace(last_obs=off.traj.last_obs[idx])
    sidx, sok = buffers.pick_rows(k2, jnp.isfinite(skilled.returns), config.skilled_trajectories)
    return TaskBatch(buffers.OffPolicyStore(traj, ok), jnp.take(skilled.obs, sidx, axis=1),
                     jnp.take(skilled.action, sidx, axis=1), jnp.take(skilled.valid, sidx, axis=1) * sok)


def _slot_batches(config: MetaConfig, stores: buffers.SequenceStores, rng, slots) -> TaskBatch:
    """Samples for the given slots; slot j always draws with ``fold_in(rng, j)``, whatever else is sampled."""
    def one(slot):
        pick = lambda x: jax.lax.dynamic_index_in_dim(x, slot, keepdims=False)  # noqa: E731
        return _sample_slot(config, jax.random.fold_in(rng, slot), jax.tree.map(pick, stores.skilled),
                            jax.tree.map(pick, stores.offpolicy))

    return jax.vmap(one)(slots)


def sample_batches(config: MetaConfig, stores: buffers.SequenceStores, rng) -> TaskBatch:
    """Samples each slot's inner (D_j) and outer (D*_j) trajectories; leading axis [num_slots]."""
    return _slot_batches(config, stores, rng, jnp.arange(stores.task_valid.shape[0]))


def task_chunk(config: MetaConfig, num_slots: int) -> int:
    """Slots per loop iteration of ``meta_gradients``: the config's, or 1 on CPU and up to 8 on accelerators."""
    chunk = config.task_chunk or (1 if jax.default_backend() == "cpu" else 8)
    return min(chunk, num_slots)


def _seen(task_valid):
    """(end, count) of bool[num_slots] ``task_valid``: one past the last seen slot (i32[]; loops over slots stop
    there) and the number of seen slots (f32[], at least 1: the divisor of a mean over them)."""
    end = jnp.max(jnp.where(task_valid, jnp.arange(1, task_valid.shape[0] + 1), 0))
    return end, jnp.maximum(jnp.sum(task_valid.astype(jnp.float32)), 1.0)


def meta_gradients(config: MetaConfig, policy, value, stores: buffers.SequenceStores, rng):
    """(SlotStats averaged over the valid slots, ∇_policy, ∇_value), sampling each slot's batches; the stats'
    ``bc_loss`` is the meta loss.

    Equal to ``jax.value_and_grad(meta_loss)`` (and the value-head l2 gradient) on ``sample_batches(config,
    stores, rng)``, but computed by a loop over chunks of ``task_chunk`` slots that stops after the last valid
    slot: nothing is spent on tasks not seen yet, and on CPU the per-slot matrix products stay unbatched (a
    batched ``[slots, n, 27] @ [slots, 27, 128]`` product is ~4x slower there than the same work slot by slot).
    Unseen slots inside the range are zeroed and their gradients dropped with ``where``, so NaN cannot leak.
    """
    task_valid = jnp.asarray(stores.task_valid)
    num_slots = task_valid.shape[0]
    chunk = task_chunk(config, num_slots)
    end, count = _seen(task_valid)
    grad_fn = jax.vmap(jax.grad(head_objective, argnums=(1, 2), has_aux=True), in_axes=(None, None, 0, 0))

    def body(c, acc):
        slots = c * chunk + jnp.arange(chunk)
        ok = (slots < num_slots) & task_valid[jnp.minimum(slots, num_slots - 1)]
        slots = jnp.minimum(slots, num_slots - 1)
        batch = _zero_unseen(_slot_batches(config, stores, rng, slots), ok)
        heads = jax.vmap(lambda j: head_params(value, j))(slots)
        (g_policy, g_heads), stats = grad_fn(config, policy, heads, batch)
        stats, g_policy, g_heads = _zero_unseen((stats, g_policy, g_heads), ok)
        acc_stats, acc_policy, acc_value = acc
        # Each head's gradient goes to its own slice of the stacked heads (a scatter-add of one head per slot,
        # not a sum of whole stacks that are zero but for one head).
        acc_value = jax.tree.map(lambda a, g: a.at[slots].add(g), acc_value, g_heads)
        return (jax.tree.map(lambda a, x: a + jnp.sum(x, axis=0), acc_stats, stats),
                jax.tree.map(lambda a, x: a + jnp.sum(x, axis=0), acc_policy, g_policy), acc_value)

    zero = jnp.zeros((), jnp.float32)
    zeros = (SlotStats(*[zero] * len(SlotStats._fields)), jax.tree.map(jnp.zeros_like, policy),
             jax.tree.map(jnp.zeros_like, value))
    stats, g_policy, g_value = jax.lax.fori_loop(0, (end + chunk - 1) // chunk, body, zeros)
    scale = lambda tree: jax.tree.map(lambda x: x / count, tree)  # noqa: E731
    return scale(stats), scale(g_policy), scale(g_value)


class MetaState(NamedTuple):
    """policy, value heads and their Adam states."""

    policy: dict
    value: list
    policy_opt: optax.OptState
    value_opt: optax.OptState


def optimizers(config: MetaConfig):
    """(outer policy optimiser, value optimiser)."""
    value_lr = 1e-3 if config.value_learning_rate is None else config.value_learning_rate
    return optax.adam(config.outer_learning_rate), optax.adam(value_lr)


def slot_gradients(config: MetaConfig, policy, value, stores: buffers.SequenceStores, rng, slot):
    """(SlotStats, ∇_policy, ∇_value) of task slot ``slot`` alone, its batches drawn as ``meta_gradients`` draws
    them (``fold_in(rng, slot)``): the per-task gradient of the ``sequential`` outer update."""
    batch = jax.tree.map(lambda x: x[0], _slot_batches(config, stores, rng, jnp.reshape(slot, (1,))))
    grads, stats = jax.grad(slot_objective, argnums=(1, 2), has_aux=True)(config, policy, value, slot, batch)
    return stats, grads[0], grads[1]


def meta_train(config: MetaConfig, state: MetaState, stores: buffers.SequenceStores, rng,
               progress_fn: Optional[ProgressFn] = None):
    """``num_meta_steps`` × ``num_outer_steps`` outer steps over the seen tasks; returns (state, SlotStats with
    fields f32[steps]: the means over the seen tasks at each outer step, on that step's batches, before its
    update; ``bc_loss`` is NaN where an update was skipped).

    ``outer_update="mean"``: each outer step is one Adam step on the mean over seen tasks. ``"sequential"``
    (Algorithm 1): each meta step visits the seen tasks in order and makes ``num_outer_steps`` Adam steps on each
    task alone. Outer step (n, k) draws task j's batches from the same key in both, so the readings differ only
    in when θ moves. An update whose loss or gradient is not finite is skipped. With ``optimizer_state="reset"``
    both Adam states start fresh.

    ``progress_fn`` (``jcomps.progress``), if given, gets ``{"meta_step", "meta_steps", "bc_loss", "value_l2",
    "value_ev", "adv_abs", "rho", "inner_gain"}`` (meta-training a long sequence takes minutes on a CPU): after
    every outer step (mean), or after every meta step with ``meta_step`` counted in outer steps (sequential).
    """
    policy_opt, value_opt = optimizers(config)
    if config.optimizer_state == "reset":
        state = state._replace(policy_opt=policy_opt.init(state.policy), value_opt=value_opt.init(state.value))
    steps = config.num_meta_steps * config.num_outer_steps
    keys = jax.random.split(rng, steps)

    def apply(state: MetaState, loss, g, vg, keep=True):
        """The Adam updates applied if ``keep`` and they are finite; (state, whether they were finite)."""
        finite = all_finite((loss, g, vg))
        policy, popt = optimizer_step(policy_opt, g, state.policy_opt, state.policy)
        value, vopt = optimizer_step(value_opt, vg, state.value_opt, state.value)
        return keep_if_finite(finite & keep, MetaState(policy, value, popt, vopt), state), finite

    def report(step, stats: SlotStats):
        if progress_fn is not None:
            progress_fn({"phase": progress.META_STEP, "meta_step": step, "meta_steps": jnp.int32(steps),
                         "bc_loss": stats.bc_loss,
                         "value_l2": stats.value_l2, "value_ev": stats.value_ev, "adv_abs": stats.adv_abs,
                         "rho": stats.rho, "inner_gain": stats.inner_gain})

    if config.outer_update == "mean":
        def outer(state: MetaState, xs):
            key, step = xs
            stats, g, vg = meta_gradients(config, state.policy, state.value, stores, key)
            report(step + 1, stats)
            state, finite = apply(state, stats.bc_loss, g, vg)
            return state, stats._replace(bc_loss=jnp.where(finite, stats.bc_loss, jnp.nan))

        return jax.lax.scan(outer, state, (keys, jnp.arange(steps, dtype=jnp.int32)))

    task_valid = jnp.asarray(stores.task_valid)
    end, count = _seen(task_valid)
    zero_stats = SlotStats(*[jnp.zeros((config.num_outer_steps,), jnp.float32)] * len(SlotStats._fields))

    def meta_step(state: MetaState, xs):
        step_keys, n = xs  # step_keys: [num_outer_steps] keys of outer steps (n, 0 ... K-1)

        def task(j, carry):
            state, total = carry

            def one(state, key):
                stats, g, vg = slot_gradients(config, state.policy, state.value, stores, key, j)
                state, finite = apply(state, stats.bc_loss, g, vg, keep=task_valid[j])
                return state, stats._replace(bc_loss=jnp.where(finite, stats.bc_loss, jnp.nan))

            state, stats = jax.lax.scan(one, state, step_keys)
            return state, jax.tree.map(lambda t, x: t + jnp.where(task_valid[j], x, 0.0), total, stats)

        state, total = jax.lax.fori_loop(0, end, task, (state, zero_stats))
        stats = jax.tree.map(lambda x: x / count, total)
        report((n + 1) * config.num_outer_steps, jax.tree.map(lambda x: x[-1], stats))
        return state, stats

    xs = (keys.reshape((config.num_meta_steps, config.num_outer_steps) + keys.shape[1:]),
          jnp.arange(config.num_meta_steps, dtype=jnp.int32))
    state, stats = jax.lax.scan(meta_step, state, xs)
    return state, jax.tree.map(lambda x: x.reshape(-1), stats)


def slot_diagnostics(config: MetaConfig, policy, value, stores: buffers.SequenceStores) -> SlotStats:
    """SlotStats of every slot on its whole D_j and D*_j (no sampling), fields f32[num_slots]; NaN in unseen slots.

    What the runner reports per task at the start and the end of each meta phase: whether each head predicts the
    returns of its task's data, and how much each task still contributes to the inner step. A loop over the seen
    slots (nothing is spent on the others).
    """
    task_valid = jnp.asarray(stores.task_valid)
    num_slots = task_valid.shape[0]
    end, _ = _seen(task_valid)
    pick = lambda tree, j: jax.tree.map(lambda x: jax.lax.dynamic_index_in_dim(x, j, keepdims=False), tree)  # noqa

    def body(j, acc):
        off, skilled = pick(stores.offpolicy, j), pick(stores.skilled, j)
        skilled_valid = skilled.valid * jnp.isfinite(skilled.returns)[None, :]
        batch = TaskBatch(off, skilled.obs, skilled.action, skilled_valid)
        stats = slot_objective(config, policy, value, j, batch)[1]
        stats = jax.tree.map(lambda x: jnp.where(task_valid[j], x, jnp.nan), stats)
        return jax.tree.map(lambda a, x: a.at[j].set(x), acc, stats)

    nan = jnp.full((num_slots,), jnp.nan, jnp.float32)
    return jax.lax.fori_loop(0, end, body, SlotStats(*[nan] * len(SlotStats._fields)))


class MetaMetrics(NamedTuple):
    """What a method with a meta step reports about the meta phase after each task (``TaskMetrics.meta``).

    Attributes:
      steps: SlotStats, fields f32[num_meta_steps · num_outer_steps]: means over the seen slots per outer step.
      start: SlotStats, fields f32[num_slots]: each slot on its whole stores before the first outer step (after
        the new task's head was initialised); NaN in unseen slots.
      end: the same after the last outer step.
    """

    steps: SlotStats
    start: SlotStats
    end: SlotStats
