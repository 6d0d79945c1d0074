"""The RL step: PPO on one task until the family's success threshold or the iteration budget.

One *iteration* (the paper's "episode" on its plots) collects ``num_trajectories`` episodes of T_max steps
with the current policy, measures the success rate, and, unless the threshold is reached, makes
``num_updates`` Adam steps on the clipped-surrogate PPO loss, each on a minibatch of ``minibatch_size``
samples (``surrogate="vanilla"`` with one full-batch step is the vanilla policy gradient of GMPS's RL step).
The iterations are ``rl_loop.iterate`` with PPO's collection and update: one ``lax.while_loop``; per-iteration
metrics come back as fixed-size arrays of length ``budget`` with a validity mask, so the whole step is one compiled
program.

Time limits are truncations: the value of the observation reached at T_max bootstraps the return, while a
termination (Ant Direction falling) does not.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, ClassVar, NamedTuple, Optional

import jax
import jax.numpy as jnp
import optax

from jcomps.envs.base import Family
from jcomps.numerics import (
    check_field, check_finite_fields, guarded_update, holds_tracers, masked_explained_variance, masked_mean,
    masked_standardize,
)
from jcomps.progress import ProgressFn
from jcomps.training import acting, networks, plasticity, rl_loop
from jcomps.training.rl_loop import IterationMetrics, UpdateTerms


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """PPO hyperparameters (paper defaults where the paper gives them)."""

    num_trajectories: int = 20
    """Episodes of T_max steps collected per iteration (paper: 20)."""
    num_updates: int = 16
    """Minibatch gradient steps per iteration (paper: "16 training updates with a batch size of 256"; read as 16
    steps, about one pass over the 4,000-sample batch, or as 16 passes, 256 steps: docs/families.md)."""
    minibatch_size: int = 256
    """Samples per gradient step (paper: 256); 0: the whole batch (T_max · num_trajectories samples)."""
    learning_rate: float = 1e-3
    """Adam learning rate (paper grid: 0.01, 5e-3, 1e-3, 1e-4)."""
    init_std: float = 0.5
    """Initial policy standard deviation (paper grid: 0.3, 0.5, 0.7, "the stochastic policy variance")."""
    std_mode: str = "learnt"
    """The policy's state-independent exploration std: ``learnt``, a parameter every update trains (PPO's, and
    the meta step's, distillation's or inner steps' of the methods that have them) and that carries over from task
    to task; ``fixed``, always ``init_std``, never trained by anything (no gradient reaches it: the authors'
    prototype, whose std is not among the policy's trainable parameters); ``reset``, learnt within a task and set
    back to ``init_std`` when a new task starts, for every method that carries parameters from task to task
    (docs/design.md, "The exploration std")."""
    hidden_sizes: tuple[int, ...] = (128, 64)
    """Hidden layer widths of the policy and value MLPs (paper: [128, 64])."""
    clip_epsilon: float = 0.2
    """PPO ratio clipping range."""
    surrogate: str = "clipped"
    """Policy loss: ``clipped``, PPO's clipped surrogate; ``vanilla``, the on-policy policy gradient −mean(log π·Â)
    with no ratio (GMPS's RL step, with one full-batch step per iteration)."""
    discount: float = 0.99
    """Discount factor γ."""
    gae_lambda: float = 0.95
    """GAE λ."""
    value_coef: float = 0.5
    """Weight of the value loss."""
    entropy_coef: float = 0.0
    """Weight of the entropy bonus."""
    max_grad_norm: float = 0.5
    """Global gradient-norm clip."""
    normalize_advantages: bool = True
    """Standardise advantages over each minibatch's valid samples."""
    normalize_observations: bool = True
    """Feed policy and value the observations standardised by running statistics (kept in the policy, updated
    after every PPO update, carried across tasks; no gradient flows into them)."""
    reward_scale: float = 1.0
    """Rewards are multiplied by this for the value targets and advantages (not for returns or success)."""
    budget: Optional[int] = None
    """Iterations per task N; None takes the family's (the paper's 500 on Half-Cheetah and MetaWorld, 1000 on the
    Ants; 300 on Point Goal)."""

    SETTINGS_PART: ClassVar[str] = "ppo"
    """Which of a family's calibrated settings apply to this config (``jcomps.envs.settings``)."""
    TRACED: ClassVar[frozenset] = frozenset({
        "learning_rate", "init_std", "clip_epsilon", "discount", "gae_lambda", "value_coef", "entropy_coef",
        "max_grad_norm", "reward_scale"})
    """Fields that may hold traced scalars (a hyperparameter-grid axis inside one compiled program); every other
    field changes shapes or Python control flow."""

    def __post_init__(self):
        if holds_tracers(self):  # a traced grid value (``numerics.holds_tracers``)
            return
        check_finite_fields(self)
        check_field(self.num_trajectories >= 1, "num_trajectories", self.num_trajectories, "an integer >= 1")
        check_field(self.num_updates >= 0, "num_updates", self.num_updates, "an integer >= 0")
        check_field(self.minibatch_size >= 0, "minibatch_size", self.minibatch_size,
                    "an integer >= 1, or 0 for the whole batch")
        check_field(self.learning_rate > 0, "learning_rate", self.learning_rate, "a number > 0")
        check_field(self.init_std > 0, "init_std", self.init_std, "a number > 0")
        check_field(self.std_mode in networks.STD_MODES, "std_mode", self.std_mode, ", ".join(networks.STD_MODES))
        check_field(len(self.hidden_sizes) >= 1 and all(h >= 1 for h in self.hidden_sizes), "hidden_sizes",
               self.hidden_sizes, "one or more positive layer widths")
        check_field(self.clip_epsilon > 0, "clip_epsilon", self.clip_epsilon, "a number > 0")
        check_field(self.surrogate in SURROGATES, "surrogate", self.surrogate, ", ".join(SURROGATES))
        check_field(0 < self.discount <= 1, "discount", self.discount, "a number in (0, 1]")
        check_field(0 <= self.gae_lambda <= 1, "gae_lambda", self.gae_lambda, "a number in [0, 1]")
        check_field(self.value_coef >= 0, "value_coef", self.value_coef, "a number >= 0")
        check_field(self.entropy_coef >= 0, "entropy_coef", self.entropy_coef, "a number >= 0")
        check_field(self.max_grad_norm > 0, "max_grad_norm", self.max_grad_norm, "a number > 0")
        check_field(self.reward_scale > 0, "reward_scale", self.reward_scale, "a number > 0")
        check_field(self.budget is None or self.budget >= 1, "budget", self.budget, "None or an integer >= 1")

    def budget_for(self, family: Family) -> int:
        """Iterations per task for ``family``."""
        return family.default_budget if self.budget is None else self.budget

    def follow(self, family: Family, keep: frozenset = frozenset()) -> "PPOConfig":
        """This config with the fields that follow another value filled, as a run records them
        (``jcomps.methods.with_followed``): ``budget`` None, the family's default budget. ``keep``: the flat field
        names a grid varies (nothing here follows one)."""
        return self if self.budget is not None else dataclasses.replace(self, budget=family.default_budget)

    def trained(self, policy: dict) -> dict:
        """``policy`` as the updates see it: with ``std_mode="fixed"`` its std is a constant of every gradient
        (``networks.held_std``), else unchanged."""
        return networks.held_std(policy) if self.std_mode == "fixed" else policy

    def task_start(self, policy: dict) -> dict:
        """The policy a new task's RL step starts from, given the one the last task left: with
        ``std_mode="reset"`` its std back at ``init_std``, else unchanged."""
        return networks.with_std(policy, self.init_std) if self.std_mode == "reset" else policy


SURROGATES = ("clipped", "vanilla")


class PPOBased:
    """Base of a method config whose RL step is PPO, held in its field ``ppo``: ``collection()`` (what every method
    config has, ``jcomps.methods.base.collection``) is that part."""

    def collection(self) -> PPOConfig:
        return self.ppo


class RLStepResult(NamedTuple):
    """What the RL step returns.

    Attributes:
      params: ActorCriticParams after the last update.
      opt_state: the Adam state after the last update.
      metrics: IterationMetrics with fields f32[budget].
      iterations: i32[], iterations-to-success: the iteration (1-based) at which the success rate first
        reached the threshold, or ``budget`` if it never did.
      solved: bool[], whether the threshold was reached.
      aux: whatever the ``observe`` hook accumulated (None without a hook).
      health: ``plasticity.PolicyHealth`` of the policy the step started from and the one it ended with.
    """

    params: networks.ActorCriticParams
    opt_state: Any
    metrics: IterationMetrics
    iterations: jax.Array
    solved: jax.Array
    aux: Any
    health: plasticity.PolicyHealth


def make_optimizer(config: PPOConfig) -> optax.GradientTransformation:
    """Adam with global-norm clipping."""
    return optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.adam(config.learning_rate))


def init_params(config: PPOConfig, family: Family, rng: jax.Array) -> networks.ActorCriticParams:
    """Fresh actor-critic parameters for ``family``."""
    return networks.init_actor_critic(rng, family.obs_size, family.action_size, config.hidden_sizes,
                                      config.init_std)


def gae(rewards, values, bootstrap_value, dones, discount: float, lambda_: float):
    """Generalised advantage estimation over time-major ``[T, B]`` arrays.

    ``values`` f32[T, B] are V(obs_t); ``bootstrap_value`` f32[B] is V(obs_T), the value of the state reached
    at the time limit (a truncation); ``dones`` f32[T, B] are 1 where a transition terminated, which cuts both
    the bootstrap and the trace. Returns (advantages f32[T, B], value targets f32[T, B]).
    """
    next_values = jnp.concatenate([values[1:], bootstrap_value[None]], axis=0)
    not_done = 1.0 - dones
    deltas = rewards + discount * not_done * next_values - values

    def body(acc, xs):
        delta, nd = xs
        acc = delta + discount * lambda_ * nd * acc
        return acc, acc

    _, advantages = jax.lax.scan(body, jnp.zeros_like(bootstrap_value), (deltas, not_done), reverse=True)
    return advantages, advantages + values




def ppo_loss(params: networks.ActorCriticParams, batch: dict, config: PPOConfig,
             policy_fns: networks.PolicyFns = networks.GAUSSIAN) -> tuple[jax.Array, UpdateTerms]:
    """PPO loss (clipped surrogate, or the vanilla policy gradient) on a flat minibatch, the policy applied by
    ``policy_fns``; returns (loss, its UpdateTerms: policy loss, value loss, entropy, approximate KL)."""
    mask = batch["valid"]
    adv = batch["advantage"]
    if config.normalize_advantages:
        adv = masked_standardize(adv, mask)
    mean, log_std = policy_fns.dist(config.trained(params.policy), batch["obs"])
    log_prob = networks.gaussian_log_prob(mean, log_std, batch["action"])
    log_ratio = log_prob - batch["log_prob"]
    ratio = jnp.exp(log_ratio)
    if config.surrogate == "vanilla":
        policy_loss = -masked_mean(log_prob * adv, mask)
    else:
        clipped = jnp.clip(ratio, 1 - config.clip_epsilon, 1 + config.clip_epsilon)
        policy_loss = -masked_mean(jnp.minimum(ratio * adv, clipped * adv), mask)
    value_loss = 0.5 * masked_mean(jnp.square(networks.value_of(params, batch["obs"]) - batch["target"]), mask)
    entropy = networks.gaussian_entropy(log_std)
    approx_kl = masked_mean(ratio - 1.0 - log_ratio, mask)
    loss = policy_loss + config.value_coef * value_loss - config.entropy_coef * entropy
    # The critic's fit is measured once per iteration on the whole batch (``batch_value_ev``), not per minibatch.
    return loss, UpdateTerms(policy_loss, value_loss, entropy, approx_kl, jnp.float32(jnp.nan))




def flat_batch(config: PPOConfig, params: networks.ActorCriticParams, traj: acting.Trajectory) -> dict:
    """One batch's samples flattened to [T·B, ...] (``obs``, ``action``, ``log_prob``, ``valid``) with their GAE
    ``advantage`` and value ``target`` under ``params``' value network (reward-scaled; the bootstrap at T_max is
    the truncation's) and that network's ``value``."""
    values = networks.value_of(params, traj.obs)
    bootstrap = networks.value_of(params, traj.last_obs)
    advantage, target = gae(traj.reward * config.reward_scale, values, bootstrap, traj.done, config.discount,
                            config.gae_lambda)
    flat = {
        "obs": traj.obs, "action": traj.action, "log_prob": traj.log_prob, "valid": traj.valid,
        "advantage": advantage, "target": target, "value": values,
    }
    return jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), flat)


def minibatch_indices(config: PPOConfig, n: int, rng: jax.Array) -> jax.Array:
    """i32[num_updates, minibatch] sample indices into a batch of ``n``: minibatches walk through fresh
    permutations of the samples, so each is used about equally (``minibatch_size`` 0: the whole batch)."""
    minibatch = config.minibatch_size or n
    total = config.num_updates * minibatch
    n_perm = max(1, -(-total // n))
    perms = jax.vmap(lambda k: jax.random.permutation(k, n))(jax.random.split(rng, n_perm))
    return perms.reshape(-1)[:total].reshape(config.num_updates, minibatch)


def minibatch_steps(config: PPOConfig, optimizer, loss_fn: Callable, params, opt_state, n: int, rng: jax.Array):
    """``num_updates`` guarded Adam steps (``numerics.guarded_update``) of ``loss_fn(params, idx) -> (loss,
    UpdateTerms)`` on minibatches ``idx`` i32[minibatch] of ``n`` samples (``minibatch_indices``). Returns (params,
    opt_state, the mean UpdateTerms, nonfinite bool[]: whether a step was skipped)."""
    grad_fn = jax.value_and_grad(loss_fn, has_aux=True)

    def step(carry, idx):
        params, opt_state, bad = carry
        (loss, terms), grads = grad_fn(params, idx)
        params, opt_state, finite = guarded_update(optimizer, grads, opt_state, params, loss)
        return (params, opt_state, bad | ~finite), terms

    indices = minibatch_indices(config, n, rng)
    (params, opt_state, bad), terms = jax.lax.scan(step, (params, opt_state, jnp.array(False)), indices)
    return params, opt_state, rl_loop.mean_terms(terms), bad


def update_obs_norm(config: PPOConfig, params: networks.ActorCriticParams, obs: jax.Array, valid: jax.Array):
    """``params`` with its policy's running observation statistics updated with ``obs`` [T, B, obs_size] where
    ``valid`` [T, B] (unchanged unless ``normalize_observations``)."""
    if not config.normalize_observations:
        return params
    norm = networks.obs_norm_update(params.policy["obs_norm"], obs, valid)
    return params._replace(policy={**params.policy, "obs_norm": norm})


def ppo_update(config: PPOConfig, optimizer, params, opt_state, traj: acting.Trajectory, rng: jax.Array,
               policy_fns: networks.PolicyFns = networks.GAUSSIAN):
    """``num_updates`` minibatch Adam steps on one iteration's batch (``flat_batch``, ``minibatch_steps``) of the
    loss of the policy ``policy_fns`` applies (``ppo_loss``).

    A step whose loss or gradient is not finite is skipped. Returns (params, opt_state, the mean UpdateTerms with
    ``value_ev`` the critic's fit to the whole batch's targets before the update (``batch_value_ev``), nonfinite
    bool[]).
    """
    flat = flat_batch(config, params, traj)
    loss_fn = lambda p, idx: ppo_loss(p, jax.tree.map(lambda x: x[idx], flat), config, policy_fns)  # noqa: E731
    params, opt_state, terms, bad = minibatch_steps(config, optimizer, loss_fn, params, opt_state,
                                                    flat["valid"].shape[0], rng)
    return params, opt_state, terms._replace(value_ev=batch_value_ev(flat)), bad


def batch_value_ev(flat: dict) -> jax.Array:
    """f32[]: the explained variance of a ``flat_batch``'s value targets by the values it was built with."""
    return masked_explained_variance(flat["target"], flat["value"], flat["valid"])


ObserveFn = Callable[[Any, acting.Trajectory, jax.Array], Any]


def rl_step(config: PPOConfig, family: Family, params: networks.ActorCriticParams, opt_state, task,
            rng: jax.Array, observe: Optional[ObserveFn] = None, aux: Any = None,
            progress_fn: Optional[ProgressFn] = None, stop_at_threshold: bool = True,
            budget: Optional[int] = None, run_at_least: Optional[int] = None,
            policy_fns: networks.PolicyFns = networks.GAUSSIAN) -> RLStepResult:
    """PPO on ``task`` until the success rate reaches ``family.success_threshold`` or the budget is spent.

    ``observe(aux, trajectory, iteration) -> aux``, if given, sees every iteration's batch (the experience
    stores of CoMPS are built this way) and threads ``aux`` through the loop. ``progress_fn``, ``stop_at_threshold``
    and ``run_at_least`` are ``rl_loop.iterate``'s. ``budget`` overrides the config's. ``policy_fns`` applies
    ``params.policy`` (default: the Gaussian MLP policy; Progress & Compress's active column brings its own).
    Jittable; ``config``, ``family`` and ``policy_fns`` are static.
    """
    budget = config.budget_for(family) if budget is None else budget
    optimizer = make_optimizer(config)
    actor = acting.actor_of(policy_fns)

    def collect(learner, aux, keys, it):
        traj = acting.rollout(family, learner[0].policy, task, keys[0], config.num_trajectories, actor)
        aux = aux if observe is None else observe(aux, traj, it)
        return learner, aux, rl_loop.collected(family, traj, traj)

    def update(learner, traj, key):
        params, opt_state, terms, bad = ppo_update(config, optimizer, *learner, traj, key, policy_fns)
        return (update_obs_norm(config, params, traj.obs, traj.valid), opt_state), terms, bad

    out = rl_loop.iterate(collect, update, (params, opt_state), rng, threshold=family.success_threshold,
                          budget=budget, aux=aux, progress_fn=progress_fn, stop_at_threshold=stop_at_threshold,
                          run_at_least=run_at_least, states=plasticity.empty_states(family, config.num_trajectories))
    health = plasticity.policy_health(policy_fns, params.policy, out.state[0].policy, out.first_states,
                                      out.last_states)
    return RLStepResult(*out.state, out.metrics, out.iterations, out.solved, out.aux, health)
