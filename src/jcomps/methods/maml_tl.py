"""MAML+TL: on-policy MAML (Finn et al. 2017, policy-gradient version) in online mode, meta-training only on the
latest task; θ carries over to the next task (the paper's "Prior methods": MAML+TL).

One iteration on task i:

1. collect ``num_trajectories`` episodes with θ (the pre-update batch);
2. inner step φ = θ + α ∇_θ J(θ), J(θ) = mean log π_θ(a|s) Â (the vanilla policy-gradient objective; or ProMP's
   importance-weighted ``lvc`` objective, ``inner_objective``) with GAE advantages from the value network
   (constants: the baseline), normalised like PPO's;
3. collect ``num_trajectories`` episodes with φ (the post-update batch); the iteration's success rate is φ's:
   it is what iterations-to-success counts;
4. unless the threshold is reached, ``num_updates`` Adam steps (``minibatch_size`` samples of the post-update
   batch each) on PPO's clipped surrogate of φ(θ) — φ recomputed from θ on the whole pre-update batch at every
   step, so the gradient flows *through* the inner step (second order unless ``first_order``) — plus the value
   loss on both batches.

An iteration collects twice the env steps of a PPO iteration (``Method.env_steps_per_iteration``). The state's
``params`` hold θ, which the next task starts from; the evaluations read what MAML reports, the adapted policy
(docs/log.md, "MAML+TL"):

- ``policy_for`` (backward transfer, replays): φ after one inner step from θ on ``num_trajectories`` fresh
  episodes of the evaluated task, as in training's steps 1–2;
- ``adapt`` (the held-out meta-test): entry 0 is θ (zero-shot), entry n the policy after n inner steps, each on
  the batch the previous entry's policy collected (so entry 1 is training's post-update policy, and each entry
  costs one batch, as a PPO iteration of the other methods' meta-test).
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, NamedTuple, Optional

import jax
import jax.numpy as jnp

from jcomps.envs.base import Family
from jcomps.methods.base import Method, TaskMetrics
from jcomps.numerics import (
    all_finite, check_field, check_finite_fields, holds_tracers, keep_if_finite, masked_mean, masked_standardize,
)
from jcomps.progress import ProgressFn, with_fields
from jcomps.training import acting, networks, plasticity, ppo, rl_loop
from jcomps.training.rl_loop import UpdateTerms


@dataclasses.dataclass(frozen=True)
class MAMLTLConfig(ppo.PPOBased):
    """Configuration of MAML+TL. The outer update is PPO's (``ppo``: clipping, steps, minibatch, Adam learning
    rate — the outer learning rate is ``ppo.learning_rate``, grid field ``learning_rate``)."""

    ppo: ppo.PPOConfig = ppo.PPOConfig()
    """Sampling (``num_trajectories`` per batch; two batches per iteration), advantages, and the outer update."""
    inner_learning_rate: float = 0.01
    """α, the inner policy-gradient step size. Finn et al. 2017 used 0.1 (with TRPO as the meta-optimiser); with
    PPO's outer update on the first stationary Point Goal task, 0.1 left one of 3 seeds at success 0 after 300
    iterations, 0.01 and 0.001 solved all (docs/design.md, "MAML+TL")."""
    first_order: bool = False
    """Stop the gradient through the inner step (first-order MAML)."""
    inner_objective: str = "vpg"
    """The inner step's objective J: ``vpg``, mean log π_θ(a|s) Â (Finn et al. 2017; its Hessian lacks the
    ∇log π ∇log πᵀ Â term, and from the second outer step on θ is no longer the batch's behaviour policy), or
    ``lvc``, mean π_θ(a|s)/π_b(a|s) Â with π_b the pre-update batch's behaviour policy (ProMP's low-variance
    curvature objective, Rothfuss et al. 2019): the same step at the behaviour policy, the full curvature, and
    importance-weighted as θ moves during the outer update."""
    reset_optimizer: bool = True
    """Start each task with a fresh Adam state (θ is always carried over)."""

    TRACED: ClassVar[frozenset] = frozenset({"inner_learning_rate"})
    """Fields that may hold traced scalars (a hyperparameter-grid axis)."""

    def __post_init__(self):
        if holds_tracers(self):  # a traced grid value (``numerics.holds_tracers``)
            return
        check_finite_fields(self)
        check_field(self.inner_learning_rate > 0, "inner_learning_rate", self.inner_learning_rate, "a number > 0")
        check_field(self.inner_objective in ("vpg", "lvc"), "inner_objective", self.inner_objective,
                    "'vpg' or 'lvc'")


class MAMLTLState(NamedTuple):
    """params: ActorCriticParams (policy θ, value); opt_state: Adam; rng; task_index: i32[]."""

    params: networks.ActorCriticParams
    opt_state: Any
    rng: jax.Array
    task_index: jax.Array


def inner_step(config: MAMLTLConfig, policy: dict, pre: dict) -> dict:
    """φ = θ + α ∇_θ J(θ), J(θ) = mean log π_θ(a|s) Â (``inner_objective`` ``vpg``) or mean π_θ(a|s)/π_b(a|s) Â
    (``lvc``, π_b's log-probabilities ``pre["log_prob"]``) over the valid samples of the flat pre-update batch
    ``pre`` (advantages normalised if ``ppo.normalize_advantages``). Differentiable in ``policy`` (second order)
    unless ``first_order``."""
    mask = pre["valid"]
    adv = pre["advantage"]
    if config.ppo.normalize_advantages:
        adv = masked_standardize(adv, mask)
    adv = jax.lax.stop_gradient(adv)
    log_prob = lambda p: networks.GAUSSIAN.log_prob(config.ppo.trained(p), pre["obs"], pre["action"])  # noqa: E731
    if config.inner_objective == "lvc":
        behaviour = jax.lax.stop_gradient(pre["log_prob"])
        objective = lambda p: masked_mean(jnp.exp(log_prob(p) - behaviour) * adv, mask)  # noqa: E731
    else:
        objective = lambda p: masked_mean(log_prob(p) * adv, mask)  # noqa: E731
    grads = jax.grad(objective)(policy)
    if config.first_order:
        grads = jax.lax.stop_gradient(grads)
    return jax.tree.map(lambda p, g: p + config.inner_learning_rate * g, policy, grads)


def adapt_on(config: MAMLTLConfig, family: Family, params: networks.ActorCriticParams, policy: dict, task,
             rng: jax.Array) -> tuple[dict, dict, acting.Trajectory]:
    """One inner step of ``policy`` on ``task``: ``num_trajectories`` episodes with ``policy`` (key ``rng``), GAE
    advantages from ``params.value`` (the baseline training fits), then ``inner_step``. Returns (the adapted
    policy, the flat batch, the episodes). With ``policy`` = ``params.policy`` it is training's steps 1–2 (which
    call it)."""
    traj = acting.rollout(family, policy, task, rng, config.ppo.num_trajectories)
    pre = ppo.flat_batch(config.ppo, networks.ActorCriticParams(policy, params.value), traj)
    return inner_step(config, policy, pre), pre, traj


def outer_loss(config: MAMLTLConfig, params: networks.ActorCriticParams, pre: dict, post: dict
               ) -> tuple[jax.Array, UpdateTerms]:
    """PPO's loss of the adapted policy φ(θ) on the (minibatch of the) post-update batch ``post``, with the value
    loss averaged over ``post`` and ``pre["minibatch"]`` (the same samples' share of the pre-update batch), so the
    value term weighs what it weighs in PPO; returns (loss, its UpdateTerms). Its gradient in ``params.policy`` is
    the MAML meta-gradient."""
    adapted = networks.ActorCriticParams(inner_step(config, params.policy, pre["full"]), params.value)
    loss, terms = ppo.ppo_loss(adapted, post, config.ppo)  # its value term: value_coef · terms.value_loss
    pre_mb = pre["minibatch"]
    pre_vl = 0.5 * masked_mean(jnp.square(networks.value_of(params, pre_mb["obs"]) - pre_mb["target"]),
                               pre_mb["valid"])
    value_loss = 0.5 * (terms.value_loss + pre_vl)
    # (No dataclasses.replace of the config here: its fields may be traced grid values.)
    return loss + config.ppo.value_coef * (value_loss - terms.value_loss), terms._replace(value_loss=value_loss)


def make(family: Family, config: MAMLTLConfig = MAMLTLConfig(), progress_fn: Optional[ProgressFn] = None) -> Method:
    pcfg = config.ppo
    optimizer = ppo.make_optimizer(pcfg)
    budget = pcfg.budget_for(family)
    B = pcfg.num_trajectories

    def init(rng: jax.Array) -> MAMLTLState:
        rng, k = jax.random.split(rng)
        params = ppo.init_params(pcfg, family, k)
        return MAMLTLState(params, optimizer.init(params), rng, jnp.int32(0))

    def update(learner, batch, key):  # step 4: the outer update, then the statistics of both batches
        params, opt_state = learner
        pre, pre_traj, post_traj = batch
        post = ppo.flat_batch(pcfg, params, post_traj)
        take = lambda d, idx: jax.tree.map(lambda x: x[idx], d)  # noqa: E731
        loss_fn = lambda p, idx: outer_loss(config, p, {"full": pre, "minibatch": take(pre, idx)},  # noqa: E731
                                            take(post, idx))
        params, opt_state, terms, bad = ppo.minibatch_steps(pcfg, optimizer, loss_fn, params, opt_state,
                                                            post["valid"].shape[0], key)
        terms = terms._replace(value_ev=ppo.batch_value_ev(post))  # the post-update batch, before the update
        obs = jnp.concatenate([pre_traj.obs, post_traj.obs], axis=1)
        valid = jnp.concatenate([pre_traj.valid, post_traj.valid], axis=1)
        return (ppo.update_obs_norm(pcfg, params, obs, valid), opt_state), terms, bad

    def learn_task(state: MAMLTLState, task) -> tuple[MAMLTLState, TaskMetrics]:
        def collect(learner, aux, keys, it):  # training's steps 1-3
            params = learner[0]
            adapted, pre, pre_traj = adapt_on(config, family, params, params.policy, task, keys[0])
            post_traj = acting.rollout(family, adapted, task, keys[1], B)
            return learner, aux, rl_loop.collected(family, (pre, pre_traj, post_traj), post_traj, pre_traj)

        rng, k_task = jax.random.split(state.rng)
        start = state.params._replace(policy=pcfg.task_start(state.params.policy))
        opt_state = optimizer.init(start) if config.reset_optimizer else state.opt_state
        report = with_fields(progress_fn, task=state.task_index)
        out = rl_loop.iterate(collect, update, (start, opt_state), k_task, threshold=family.success_threshold,
                              budget=budget, collect_keys=2, progress_fn=report,
                              states=plasticity.empty_states(family, B))
        params, opt_state = out.state
        health = plasticity.policy_health(networks.GAUSSIAN, start.policy, params.policy, out.first_states,
                                          out.last_states)
        return MAMLTLState(params, opt_state, rng, state.task_index + 1), TaskMetrics(out.iterations, out.solved,
                                                                                      out.metrics,
                                                                                      policy_health=health)

    def policy_for(state: MAMLTLState, slot, task, rng):  # φ: one inner step from θ on fresh data of ``task``
        return adapt_on(config, family, state.params, state.params.policy, task, rng)[0]

    def adapt(state: MAMLTLState, task, rng, iterations: int):
        """Entry n: ``num_trajectories`` episodes of the policy after n inner steps from θ (entry 0: θ); each
        batch is the data of the next inner step (a step whose result is not finite is skipped)."""
        def one(policy, key):
            adapted, _, traj = adapt_on(config, family, state.params, policy, task, key)
            return keep_if_finite(all_finite(adapted), adapted, policy), rl_loop.episode_stats(family, traj)

        _, (returns, success) = jax.lax.scan(one, state.params.policy, jax.random.split(rng, iterations))
        return returns, success

    return Method("maml_tl", config, family, init, learn_task, env_steps_per_iteration=2 * B * family.max_steps,
                  policy_for=policy_for, adapt=adapt)
