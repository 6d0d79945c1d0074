"""The RL step's loop: iterate collect → measure → update on one task until the success threshold or the budget.

Every method's RL step is this loop with its own two functions (as brax composes its trainer from a loss and
``gradient_update_fn``): PPO's (``ppo.rl_step``: one batch, minibatch Adam steps), MAML+TL's (a pre- and a
post-update batch, the meta-gradient through the inner step) and PEARL's (SAC steps on the replay buffers). The loop
owns what they share:

- the iteration's keys: ``split(rng, 2 + collect_keys)`` gives the next carry key, ``collect_keys`` keys for the
  collection and one for the update;
- the success rate and mean return of the iteration's episodes, the progress event (``progress.ITERATION``, after
  the update, with the critic's fit the update measured);
- the decision to update: never once the threshold is reached (iterations-to-success counts the first iteration at
  or above it; no update follows it), never on a batch holding a NaN or an infinity (flagged ``nonfinite``);
- the per-iteration metrics, fixed-size arrays of length ``budget`` with a validity mask, so the whole loop is one
  ``lax.while_loop`` in one compiled program.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp

from jcomps import progress
from jcomps.numerics import all_finite
from jcomps.progress import ProgressFn
from jcomps.training import acting
from jcomps.training.plasticity import States


class IterationMetrics(NamedTuple):
    """Per-iteration metrics; inside the loop each field is f32[budget] (bool for ``valid``).

    Attributes:
      mean_return: undiscounted return per episode, averaged over the iteration's episodes.
      success_rate: the family's success rate of the iteration.
      policy_loss, value_loss, entropy, approx_kl: ``UpdateTerms``, means over the iteration's gradient steps (0
        when the iteration reached the threshold and made no update).
      value_ev: ``UpdateTerms.value_ev``, the critic's explained variance of its value targets on the iteration's
        batch before the update (NaN where no update was made, and for methods without such a critic).
      nonfinite: 1 where the iteration produced a NaN or infinity (rollout, loss or gradient); such updates
        are skipped, never applied.
      valid: True for iterations that ran (the first ``iterations`` entries).
    """

    mean_return: jax.Array
    success_rate: jax.Array
    policy_loss: jax.Array
    value_loss: jax.Array
    entropy: jax.Array
    approx_kl: jax.Array
    value_ev: jax.Array
    nonfinite: jax.Array
    valid: jax.Array


class UpdateTerms(NamedTuple):
    """What an update reports, f32[] each: a loss's named terms (PPO's; PEARL reports its actor loss as
    ``policy_loss``, its critic loss as ``value_loss`` and the encoder's KL as ``approx_kl``), and ``value_ev``,
    how well the critic fits its value targets: 1 − Var(target − V)/Var(target) (``numerics.masked_explained_
    variance``). PPO (``ppo.ppo_update``) and MAML+TL report it on the iteration's whole batch before the update,
    against the GAE λ-returns the update regresses on (Stable-Baselines' and CleanRL's diagnostic; ``ppo.ppo_loss``,
    per minibatch, leaves it NaN for them to set); PEARL, whose critics are Q-functions of TD targets, reports NaN
    (not measured)."""

    policy_loss: jax.Array
    value_loss: jax.Array
    entropy: jax.Array
    approx_kl: jax.Array
    value_ev: jax.Array


def zero_terms() -> UpdateTerms:
    """The terms of an iteration that made no update: zero losses, the critic's fit not measured (NaN)."""
    zero = jnp.float32(0.0)
    return UpdateTerms(zero, zero, zero, zero, jnp.float32(jnp.nan))


def mean_terms(per_step: UpdateTerms) -> UpdateTerms:
    """The means over the leading (gradient-step) axis of ``per_step``'s fields f32[steps]."""
    return UpdateTerms(*jnp.mean(jnp.stack(per_step, axis=-1), axis=0))


class Collected(NamedTuple):
    """One iteration's collection, as the loop sees it.

    Attributes:
      batch: what the update learns from (the method's business).
      mean_return: f32[], the undiscounted return per episode of the episodes that measure the iteration.
      success_rate: f32[], their success rate.
      finite: bool[], whether every collected observation and reward is finite (no update otherwise).
      states: the measured episodes' ``plasticity.States`` (what the loop keeps with ``iterate(states=...)``);
        None: not given.
    """

    batch: Any
    mean_return: jax.Array
    success_rate: jax.Array
    finite: jax.Array
    states: Optional[States] = None


def episode_stats(family, traj) -> tuple[jax.Array, jax.Array]:
    """(mean return f32[], success rate f32[]) of the episodes of ``traj`` (``acting.Trajectory``, [T, B])."""
    return jnp.mean(jnp.sum(traj.reward, axis=0)), family.success_rate(traj.success, traj.valid)


def collected(family, batch, measured, *others) -> Collected:
    """The ``Collected`` of an iteration whose success and return are those of the trajectory ``measured`` and whose
    finiteness is that of ``measured`` and the trajectories ``others`` (observations and rewards)."""
    mean_return, success_rate = episode_stats(family, measured)
    finite = all_finite(tuple((t.obs, t.reward) for t in (measured, *others)))
    return Collected(batch, mean_return, success_rate, finite, States(measured.obs, measured.valid))


CollectFn = Callable[[Any, Any, tuple, jax.Array], tuple[Any, Any, Collected]]
"""``collect(state, aux, keys, iteration) -> (state, aux, Collected)``: one iteration's episodes with ``keys``
(``collect_keys`` PRNG keys). It may change the learner's ``state`` (PEARL writes its replay buffers) and ``aux``,
an accumulator the update never sees (CoMPS's experience stores; kept out of the update's ``lax.cond``)."""

UpdateFn = Callable[[Any, Any, jax.Array], tuple[Any, UpdateTerms, jax.Array]]
"""``update(state, batch, key) -> (state, UpdateTerms, nonfinite bool[])``: the iteration's gradient steps, each
skipped where it is not finite (``numerics.guarded_update``), ``nonfinite`` True if any was."""


class LoopResult(NamedTuple):
    """What ``iterate`` returns.

    Attributes:
      state: the learner's state after the last update.
      aux: the accumulator after the last collection.
      metrics: IterationMetrics with fields f32[budget].
      iterations: i32[], iterations-to-success: the first iteration (1-based) at or above the threshold, or
        ``budget`` if none was.
      solved: bool[], whether the threshold was reached.
      rng: the carry key after the last iteration.
      first_states, last_states: the ``plasticity.States`` of the first and the last iteration's measured episodes
        (with ``iterate(states=...)``; else None).
    """

    state: Any
    aux: Any
    metrics: IterationMetrics
    iterations: jax.Array
    solved: jax.Array
    rng: jax.Array
    first_states: Optional[States] = None
    last_states: Optional[States] = None


def empty_metrics(budget: int) -> IterationMetrics:
    """IterationMetrics of ``budget`` iterations, none of them run yet (zeros, ``valid`` False)."""
    zeros = jnp.zeros((budget,), jnp.float32)
    return IterationMetrics(zeros, zeros, zeros, zeros, zeros, zeros, zeros, zeros, jnp.zeros((budget,), bool))


def first_success(success_rate: jax.Array, threshold: float, cap: int) -> tuple[jax.Array, jax.Array]:
    """Iterations-to-success of a success-rate curve f32[n] run to the end: the first iteration (1-based) at or above
    ``threshold``, ``cap`` if none is; and bool[], whether one is."""
    reached = success_rate >= threshold
    solved = jnp.any(reached)
    return jnp.where(solved, jnp.argmax(reached).astype(jnp.int32) + 1, cap).astype(jnp.int32), solved


class _Carry(NamedTuple):
    state: Any
    aux: Any
    rng: jax.Array
    it: jax.Array
    solved: jax.Array
    metrics: IterationMetrics
    first: Optional[States]
    last: Optional[States]


def iterate(collect: CollectFn, update: UpdateFn, state, rng: jax.Array, *, threshold: float, budget: int,
            collect_keys: int = 1, aux: Any = None, progress_fn: Optional[ProgressFn] = None,
            stop_at_threshold: bool = True, run_at_least: Optional[int] = None,
            states: Optional[States] = None) -> LoopResult:
    """Iterations of ``collect`` then ``update`` until the success rate reaches ``threshold`` or ``budget``
    iterations ran.

    ``progress_fn`` (``jcomps.progress``), if given, gets ``{"phase": ITERATION, "iteration", "success_rate",
    "mean_return", "value_ev"}`` after every iteration (``value_ev``: ``UpdateTerms.value_ev``, NaN without an
    update). ``stop_at_threshold=False`` runs the whole budget, updating after every
    iteration (fixed-budget adaptation), or with ``run_at_least`` stops once the threshold has been reached and at
    least that many iterations ran (the metrics of the iterations run are the same either way; later ones are left
    unrun: ``valid`` False, zeros). ``states``, zeros shaped as one iteration's measured states
    (``plasticity.empty_states``), keeps the first and the last iteration's (``Collected.states``) for the plasticity
    measures. Jittable; ``collect``, ``update`` and the keyword arguments are static.
    """

    def cond(c: _Carry):
        if stop_at_threshold:
            return (~c.solved) & (c.it < budget)
        if run_at_least is None:
            return c.it < budget
        return ((~c.solved) | (c.it < run_at_least)) & (c.it < budget)

    def body(c: _Carry):
        keys = jax.random.split(c.rng, 2 + collect_keys)
        # Under vmap the loop runs this body for every member until all have stopped, discarding the stopped
        # members' results: their host-simulated rollouts are skipped and their progress events dropped.
        active = cond(c)
        with acting.only_if(active):
            state, aux, col = collect(c.state, c.aux, tuple(keys[1:-1]), c.it)
        solved = c.solved | (col.success_rate >= threshold)  # reached at this or an earlier iteration

        def learn(state):
            return update(state, col.batch, keys[-1])

        def skip(state):
            return state, zero_terms(), jnp.array(False)

        no_update = (solved & stop_at_threshold) | ~col.finite
        state, terms, bad = jax.lax.cond(no_update, skip, learn, state)
        if progress_fn is not None:
            progress_fn({"phase": progress.ITERATION, "iteration": c.it + 1, "success_rate": col.success_rate,
                         "mean_return": col.mean_return, "value_ev": terms.value_ev, "active": active})
        bad = jnp.maximum(bad.astype(jnp.float32), 1.0 - col.finite.astype(jnp.float32))
        row = IterationMetrics(col.mean_return, col.success_rate, *terms, bad, jnp.array(True))
        metrics = jax.tree.map(lambda m, v: m.at[c.it].set(v), c.metrics, row)
        first, last = c.first, c.last
        if states is not None:
            if col.states is None:
                raise ValueError("iterate(states=...) needs the collection's states (Collected.states)")
            first = jax.tree.map(lambda kept, now: jnp.where(c.it == 0, now, kept), first, col.states)
            last = col.states
        return _Carry(state, aux, keys[0], c.it + 1, solved, metrics, first, last)

    init = _Carry(state, aux, rng, jnp.int32(0), jnp.array(False), empty_metrics(budget), states, states)
    out = jax.lax.while_loop(cond, body, init)
    if stop_at_threshold:
        iterations, solved = out.it, out.solved
    else:
        iterations, solved = first_success(out.metrics.success_rate, threshold, budget)
    return LoopResult(out.state, out.aux, out.metrics, iterations, solved, out.rng, out.first, out.last)
