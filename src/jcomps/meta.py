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
from typing import ClassVar, NamedTuple, Optional

import jax
import jax.numpy as jnp
import optax

from jcomps import buffers, networks, vtrace
from jcomps.numerics import all_finite, check_field, keep_if_finite, masked_mean
from jcomps.progress import ProgressFn


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
    normalize_advantages: bool = False
    """Standardise the inner advantages per task (zero mean, unit std over its valid samples) before the
    importance weights, as GMPS's code does (``center_adv``); off: the raw advantages (docs/design.md)."""
    task_chunk: int = 0
    """Task slots computed in parallel per loop iteration of the meta step; 0: 1 on CPU, 8 on accelerators."""
    outer_update: str = "mean"
    """How θ is updated: ``mean``, one Adam step on the mean over seen tasks per outer step; ``sequential``,
    Algorithm 1 read literally: per meta step, task after task (newest last), ``num_outer_steps`` Adam steps on
    that task alone. Both make the same number of per-task gradient evaluations (docs/design.md)."""

    TRACED: ClassVar[frozenset] = frozenset({
        "outer_learning_rate", "inner_learning_rate", "value_learning_rate", "discount", "rho_bar", "c_bar",
        "pg_rho_bar"})
    """Fields that may hold traced scalars (a hyperparameter-grid axis inside one compiled program)."""

    def __post_init__(self):
        for name in ("outer_learning_rate", "inner_learning_rate", "value_learning_rate", "rho_bar", "c_bar",
                     "pg_rho_bar"):
            check_field(getattr(self, name) > 0, name, getattr(self, name), "a number > 0")
        for name in ("num_meta_steps", "num_outer_steps"):
            check_field(getattr(self, name) >= 0, name, getattr(self, name), "an integer >= 0")
        check_field(self.task_chunk >= 0, "task_chunk", self.task_chunk, "an integer >= 0 (0: by backend)")
        for name in ("inner_trajectories", "skilled_trajectories"):
            check_field(getattr(self, name) >= 1, name, getattr(self, name), "an integer >= 1")
        check_field(0 < self.discount <= 1, "discount", self.discount, "a number in (0, 1]")
        check_field(self.outer_update in OUTER_UPDATES, "outer_update", self.outer_update, ", ".join(OUTER_UPDATES))


OUTER_UPDATES = ("mean", "sequential")

# The paper's per-family meta-step settings (its table of inner learning rates: 0.005 on the MuJoCo families,
# 0.0025 on MetaWorld), put over ``MetaConfig``'s defaults by ``jcomps.methods.default_config``.
FAMILY_DEFAULTS: dict[str, dict] = {"metaworld": {"inner_learning_rate": 0.0025}}


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
    """V_slot(obs): the shared torso, then only column ``slot`` of the last layer."""
    h = networks.mlp_features(value[:-1], obs)
    return h @ value[-1]["w"][:, slot] + value[-1]["b"][slot]


def _vtrace_terms(config: MetaConfig, log_prob, values, bootstrap, off: buffers.OffPolicyStore):
    """(inner advantages f32[T, m] including clipped ρ, value targets f32[T, m]); constants (no gradient).

    With ``normalize_advantages`` the advantages are standardised over the task's valid samples before the
    importance weights multiply them (GMPS's ``center_adv``).
    """
    traj = off.traj
    discounts = config.discount * (1.0 - traj.done)
    log_rhos = log_prob - traj.log_prob if config.importance_sampling else jnp.zeros_like(traj.log_prob)
    values, bootstrap, log_rhos = jax.lax.stop_gradient((values, bootstrap, log_rhos))
    if config.vtrace_baseline:
        out = vtrace.vtrace(values, bootstrap, traj.reward, discounts, log_rhos, rho_bar=config.rho_bar,
                            c_bar=config.c_bar, pg_rho_bar=config.pg_rho_bar)
        if not config.normalize_advantages:
            return out.pg_advantages, out.vs
        weights, targets = out.clipped_pg_rhos, out.vs
        raw = traj.reward + discounts * jnp.concatenate([out.vs[1:], bootstrap[None]], axis=0) - values
    else:
        # No V-trace: the advantage is the bootstrapped discounted return minus V; importance weights (if on)
        # still weight the step.
        targets = vtrace.discounted_returns(traj.reward, discounts, bootstrap)
        weights = jnp.minimum(jnp.exp(log_rhos), config.pg_rho_bar) if config.importance_sampling else 1.0
        raw = targets - values
    if config.normalize_advantages:
        mask = traj.valid * off.mask[None, :]
        mean = masked_mean(raw, mask)
        raw = (raw - mean) / (jnp.sqrt(masked_mean(jnp.square(raw - mean), mask)) + 1e-8)
    return weights * raw, targets


def adapt(config: MetaConfig, policy, off: buffers.OffPolicyStore, advantages, log_prob_vjp):
    """φ = θ + α ∇_θ J(θ) with J the importance-weighted policy-gradient objective on ``off``.

    ``log_prob_vjp``: the VJP of θ ↦ log π_θ(a|s) on ``off`` (the caller has run that forward pass already).
    """
    mask = off.traj.valid * off.mask[None, :]
    # ∇_θ masked_mean(log π_θ · Â) is the VJP of log π_θ with cotangent Â·mask / Σmask.
    (grads,) = log_prob_vjp(advantages * mask / jnp.maximum(jnp.sum(mask), 1.0))
    if config.first_order:
        grads = jax.lax.stop_gradient(grads)
    return jax.tree.map(lambda p, g: p + config.inner_learning_rate * g, policy, grads)


def bc_loss(policy, obs, action, valid):
    """Behaviour cloning: −mean log π(a|s) over valid samples."""
    return -masked_mean(networks.policy_log_prob(policy, obs, action), valid)


def slot_objective(config: MetaConfig, policy, value, slot, batch: TaskBatch):
    """L_BC(φ_slot) + the value head's l2, and (L_BC, value l2) as aux, for one task slot.

    Its gradient in ``policy`` is the task's meta-gradient (through the inner step unless ``first_order``); in
    ``value`` it is the l2 gradient of head ``slot`` (V-trace targets and advantages are constants), so one
    backward pass serves both. The forward passes of the policy and the value head on D_j are shared between the
    importance weights, the targets, the inner objective and the value loss.
    """
    off = batch.off
    # The value heads see observations normalised like the policy's (statistics are constants).
    values = _head(value, networks.normalize_obs(policy, off.traj.obs), slot)
    bootstrap = _head(value, networks.normalize_obs(policy, off.traj.last_obs), slot)
    log_prob, log_prob_vjp = jax.vjp(lambda p: networks.policy_log_prob(p, off.traj.obs, off.traj.action), policy)
    advantages, targets = _vtrace_terms(config, log_prob, values, bootstrap, off)
    adapted = adapt(config, policy, off, advantages, log_prob_vjp)
    bc = bc_loss(adapted, batch.skilled_obs, batch.skilled_action, batch.skilled_valid)
    value_l2 = masked_mean(jnp.square(values - targets), off.traj.valid * off.mask[None, :])
    return bc + value_l2, (bc, value_l2)


def task_loss(config: MetaConfig, policy, value, slot, batch: TaskBatch):
    """L_BC(φ_j) for one task, with φ_j adapted from ``policy`` on the task's off-policy batch."""
    return slot_objective(config, policy, value, slot, batch)[1][0]


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
    """(mean L_BC, ∇_policy, ∇_value) over the valid slots, sampling each slot's batches.

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
    grad_fn = jax.vmap(jax.grad(slot_objective, argnums=(1, 2), has_aux=True), in_axes=(None, None, None, 0, 0))

    def body(c, acc):
        slots = c * chunk + jnp.arange(chunk)
        ok = (slots < num_slots) & task_valid[jnp.minimum(slots, num_slots - 1)]
        slots = jnp.minimum(slots, num_slots - 1)
        batch = _zero_unseen(_slot_batches(config, stores, rng, slots), ok)
        grads, (bc, _) = grad_fn(config, policy, value, slots, batch)
        kept = _zero_unseen((bc, grads), ok)
        return jax.tree.map(lambda a, x: a + jnp.sum(x, axis=0), acc, kept)

    zeros = jax.tree.map(jnp.zeros_like, (jnp.zeros((), jnp.float32), (policy, value)))
    loss, (g_policy, g_value) = jax.lax.fori_loop(0, (end + chunk - 1) // chunk, body, zeros)
    scale = lambda tree: jax.tree.map(lambda x: x / count, tree)  # noqa: E731
    return loss / count, scale(g_policy), scale(g_value)


class MetaState(NamedTuple):
    """policy, value heads and their Adam states."""

    policy: dict
    value: list
    policy_opt: optax.OptState
    value_opt: optax.OptState


def optimizers(config: MetaConfig):
    """(outer policy optimiser, value optimiser)."""
    return optax.adam(config.outer_learning_rate), optax.adam(config.value_learning_rate)


def slot_gradients(config: MetaConfig, policy, value, stores: buffers.SequenceStores, rng, slot):
    """(L_BC, ∇_policy, ∇_value) of task slot ``slot`` alone, its batches drawn as ``meta_gradients`` draws them
    (``fold_in(rng, slot)``): the per-task gradient of the ``sequential`` outer update."""
    batch = jax.tree.map(lambda x: x[0], _slot_batches(config, stores, rng, jnp.reshape(slot, (1,))))
    grads, (bc, _) = jax.grad(slot_objective, argnums=(1, 2), has_aux=True)(config, policy, value, slot, batch)
    return bc, grads[0], grads[1]


def meta_train(config: MetaConfig, state: MetaState, stores: buffers.SequenceStores, rng,
               progress_fn: Optional[ProgressFn] = None):
    """``num_meta_steps`` × ``num_outer_steps`` outer steps over the seen tasks; returns (state, outer losses
    f32[steps]: the mean BC loss over the seen tasks at each step, NaN where an update was skipped).

    ``outer_update="mean"``: each outer step is one Adam step on the mean over seen tasks. ``"sequential"``
    (Algorithm 1): each meta step visits the seen tasks in order and makes ``num_outer_steps`` Adam steps on each
    task alone. Outer step (n, k) draws task j's batches from the same key in both, so the readings differ only
    in when θ moves. An update whose loss or gradient is not finite is skipped.

    ``progress_fn`` (``jcomps.progress``), if given, gets ``{"meta_step", "meta_steps", "bc_loss"}`` (meta-training
    a long sequence takes minutes on a CPU): after every outer step (mean), or after every meta step with
    ``meta_step`` counted in outer steps (sequential).
    """
    policy_opt, value_opt = optimizers(config)
    steps = config.num_meta_steps * config.num_outer_steps
    keys = jax.random.split(rng, steps)

    def apply(state: MetaState, loss, g, vg, keep=True):
        """The Adam updates applied if ``keep`` and they are finite; (state, whether they were finite)."""
        finite = all_finite((loss, g, vg))
        up, popt = policy_opt.update(g, state.policy_opt, state.policy)
        vup, vopt = value_opt.update(vg, state.value_opt, state.value)
        new = MetaState(optax.apply_updates(state.policy, up), optax.apply_updates(state.value, vup), popt, vopt)
        return keep_if_finite(finite & keep, new, state), finite

    def report(step, loss):
        if progress_fn is not None:
            progress_fn({"meta_step": step, "meta_steps": jnp.int32(steps), "bc_loss": loss})

    if config.outer_update == "mean":
        def outer(state: MetaState, xs):
            key, step = xs
            loss, g, vg = meta_gradients(config, state.policy, state.value, stores, key)
            report(step + 1, loss)
            state, finite = apply(state, loss, g, vg)
            return state, jnp.where(finite, loss, jnp.nan)

        return jax.lax.scan(outer, state, (keys, jnp.arange(steps, dtype=jnp.int32)))

    task_valid = jnp.asarray(stores.task_valid)
    end, count = _seen(task_valid)

    def meta_step(state: MetaState, xs):
        step_keys, n = xs  # step_keys: [num_outer_steps] keys of outer steps (n, 0 ... K-1)

        def task(j, carry):
            state, total = carry

            def one(state, key):
                loss, g, vg = slot_gradients(config, state.policy, state.value, stores, key, j)
                state, finite = apply(state, loss, g, vg, keep=task_valid[j])
                return state, jnp.where(finite, loss, jnp.nan)

            state, losses = jax.lax.scan(one, state, step_keys)
            return state, total + jnp.where(task_valid[j], losses, 0.0)

        state, total = jax.lax.fori_loop(0, end, task, (state, jnp.zeros((config.num_outer_steps,), jnp.float32)))
        losses = total / count
        report((n + 1) * config.num_outer_steps, losses[-1])
        return state, losses

    xs = (keys.reshape((config.num_meta_steps, config.num_outer_steps) + keys.shape[1:]),
          jnp.arange(config.num_meta_steps, dtype=jnp.int32))
    state, losses = jax.lax.scan(meta_step, state, xs)
    return state, losses.reshape(-1)
