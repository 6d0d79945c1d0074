"""PEARL (Rakelly et al. 2019) in the continual setting: SAC with a probabilistic context encoder.

The pieces, and where they come from:

- **SAC** (Haarnoja et al. 2018): brax's (``brax.training.agents.sac``): its twin-Q and tanh-Gaussian policy
  networks (``make_sac_networks``: flax MLPs, ReLU, a ``NormalTanhDistribution`` with softplus scale), and its
  three losses (``make_losses``: the critic's soft Bellman target with the minimum of the two target critics, the
  actor's α log π − min Q, the temperature's). They are pure functions of a transition batch, so PEARL's latent
  enters as part of the observation and the encoder's gradient flows through the critic loss unchanged. Rewritten
  here: only the Polyak average (one line) and the masks (a row that is not a valid transition is passed to brax's
  critic loss as a "truncation", which zeroes its error).
- **The context encoder**: an MLP (brax's ``networks.MLP``) of each transition (s, a, r[, s']) to a Gaussian
  factor (μ_n, σ²_n = softplus); the posterior q(z|c) is their product, N(σ² Σ μ_n/σ²_n, 1/Σ 1/σ²_n) (PEARL's
  ``_product_of_gaussians``), permutation-invariant; a KL(q(z|c) ‖ N(0, I)) term weighted by ``kl_weight``
  regularises it. z is drawn by reparameterisation, fed to policy and critics (concatenated to the observation),
  and trained through the critic loss; the actor and the target see z with its gradient stopped (as in PEARL).

**The continual protocol.** Tasks arrive one at a time. A replay buffer per task slot (``buffers.TransitionStore``,
``buffer_size`` transitions per task, a ring) keeps every task's data; slot i is task i of the sequence. Each
iteration on task i:

1. draws z from the posterior of a context of ``context_size`` transitions sampled from slot i (from the prior
   N(0, I) while slot i is empty, at the task's first iteration), one z per episode;
2. collects ``num_trajectories`` episodes of T_max steps on task i with it (the same env steps per iteration as
   the PPO methods), whose success rate is the iteration's (iterations-to-success as PPO's: the first iteration
   at or above the threshold; no update follows it);
3. adds them to slot i;
4. makes ``num_updates`` gradient steps, each on ``meta_batch`` task slots drawn uniformly from the slots seen so
   far (i included; ``current_slots`` of them can be fixed to slot i), with a context of ``context_size`` and a
   batch of ``minibatch_size`` transitions per slot.

Everything is fixed-size arrays and ``lax`` loops: vmapped over seeds and checkpointed like every method (the
buffers are part of the state, so a resume is exact).

Evaluations: ``policy_for(state, slot)`` acts with z from the posterior of slot's context (backward transfer);
``adapt`` is PEARL's meta-test on a held-out task, adaptation by inference with no gradient step: iteration 0 acts
with z from the prior, iteration n with z from the posterior of a context sampled from iteration n − 1's batch.

IterationMetrics fields: ``policy_loss`` is the actor loss, ``value_loss`` the critic loss, ``entropy`` the mean
−log π of the actor's samples, ``approx_kl`` the mean KL(q(z|c) ‖ N(0, I)) (all means over the iteration's steps);
``value_ev`` is NaN (the Q-critics' fit is their loss).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, ClassVar, NamedTuple, Optional

import jax
import jax.numpy as jnp
import optax
from brax.training import networks as brax_networks
from brax.training import types as brax_types
from brax.training.agents.sac import losses as sac_losses
from brax.training.agents.sac import networks as sac_networks

from jcomps.envs.base import Family
from jcomps.methods.base import Method, TaskMetrics
from jcomps.numerics import (
    all_finite, check_field, check_finite_fields, holds_tracers, keep_if_finite, masked_mean, masked_weights,
    optimizer_step,
)
from jcomps.progress import ProgressFn, with_fields
from jcomps.training import acting, buffers, networks, rl_loop


@dataclasses.dataclass(frozen=True)
class PEARLConfig:
    """Configuration of PEARL (defaults: oyster's ``configs/default.py`` where it has the field)."""

    num_trajectories: int = 20
    """Episodes of T_max steps collected per iteration (as the PPO methods, so iterations compare)."""
    budget: Optional[int] = None
    """Iterations per task N; None takes the family's paper value."""
    num_updates: Optional[int] = None
    """Gradient steps per iteration (a tuning axis: ``--grid num_updates=...``); None: ``updates_per_step`` times
    the env steps the iteration collects. A CPU-sized setting is 64 (docs/design.md)."""
    updates_per_step: float = 0.5
    """Gradient steps per env step collected, when ``num_updates`` is None: oyster's ratio, 2,000 steps per round of
    5 tasks × 800 transitions (``configs/default.py``; its point robot: 1,000 per 5 × 400; its Ant configs 4,000
    per 5 × 1,000 = 0.8; its cheetah-vel 2,000 per 5 × 1,000 = 0.4: the families' defaults)."""
    minibatch_size: int = 256
    """Transitions per task slot in each gradient step's RL batch (oyster: batch_size 256)."""
    meta_batch: int = 4
    """Task slots per gradient step, drawn uniformly from those seen (oyster: 16 tasks of its training set)."""
    current_slots: int = 0
    """Of each gradient step's ``meta_batch`` slots, this many are the task being learnt, the rest drawn uniformly
    from those seen. 0 is oyster's uniform draw, under which the task being learnt gets on average
    ``meta_batch / i`` of the slots at task i; 1 keeps at least a ``1 / meta_batch`` share of every step for it
    (the second reading of the paper's continual PEARL, docs/design.md)."""
    context_size: int = 64
    """Transitions in a context (oyster: embedding_batch_size 64; 100 in its cheetah-vel, 256 in its Ant configs)."""
    context_source: str = "prior"
    """Where contexts come from. ``prior``: oyster's encoder buffer, one per task slot, emptied at every iteration
    and filled with that iteration's episodes collected with z from the prior (the first ``prior_fraction`` of the
    episodes); the other episodes act with z from the posterior of contexts drawn from it and go to the replay
    buffer only (oyster's ``num_extra_rl_steps_posterior``, ``add_to_enc_buffer=False``), and the iteration's
    success rate is theirs. ``replay``: contexts drawn from the slot's whole replay buffer, every episode acting with
    z from its posterior (a simpler reading of the paper)."""
    prior_fraction: float = 0.5
    """With ``context_source="prior"``: the share of each iteration's ``num_trajectories`` episodes collected with
    z from the prior (oyster: ``num_steps_prior`` 400 of 800 per round; 400 of 1,000 in its Ant and cheetah-vel
    configs)."""
    initial_steps: int = 2000
    """Env steps collected with z from the prior into a task's replay buffer before its first iteration, rounded
    up to whole episodes (oyster's ``num_initial_steps``: 2,000; 200 for its point robot); counted in the task's
    samples (``Method.env_steps_before_task``); 0: none."""
    latent_size: int = 5
    """Size of the latent z (oyster: 5)."""
    kl_weight: float = 1.6
    """Weight of the mean over a gradient step's task slots of KL(q(z|c) ‖ N(0, I)) against the critics' loss (a
    mean over all rows). oyster sums the KL over its meta-batch of tasks and means the Bellman error over all their
    rows, so per task the KL weighs ``kl_lambda`` × its meta-batch against that task's share of the Bellman loss:
    0.1 × 16 = 1.6 (``configs/default.py``), 1.0 × 10 = 10 (``ant-goal.json``), 0.1 × 4 = 0.4 (``ant-dir.json``).
    With this convention the weight does not depend on our ``meta_batch``."""
    hidden_sizes: tuple[int, ...] = (300, 300, 300)
    """Hidden layers of the policy and of each critic (oyster: net_size 300, three layers)."""
    encoder_hidden_sizes: tuple[int, ...] = (200, 200, 200)
    """Hidden layers of the context encoder (oyster: 200, three layers)."""
    learning_rate: float = 3e-4
    """Adam learning rate of policy, critics, encoder and temperature (oyster: 3e-4 for each)."""
    discount: float = 0.99
    """Discount factor γ."""
    tau: float = 0.005
    """Polyak rate of the target critics (oyster: soft_target_tau 0.005)."""
    reward_scale: float = 5.0
    """Rewards are multiplied by this in the soft Bellman target (oyster: 5; with α = 1 it sets the entropy's
    weight)."""
    policy_reg: float = 1e-3
    """Weight of oyster's policy regularisers, the mean square of the pre-tanh mean and of its log-scale."""
    alpha: float = 1.0
    """Entropy temperature α when ``auto_alpha`` is off (oyster: 1, with the reward scale)."""
    auto_alpha: bool = False
    """Learn α towards the target entropy −A/2 (brax's SAC), starting from ``alpha``."""
    context_next_obs: bool = True
    """Transitions in the context include s' (the issue's (s, a, r, s'); oyster's default leaves it out)."""
    buffer_size: int = 50_000
    """Transitions kept per task slot (a ring, rounded down to whole iterations' batches, at least one)."""
    max_tasks: int = 40
    """Task slots of the replay buffers: the longest sequence the method can learn."""

    SETTINGS_PART: ClassVar[str] = "pearl"
    """Which of a family's calibrated settings apply to this config (oyster's, ``jcomps.envs.settings``)."""
    TRACED: ClassVar[frozenset] = frozenset({"learning_rate", "discount", "tau", "reward_scale", "kl_weight",
                                             "alpha", "policy_reg"})
    """Fields that may hold traced scalars (a hyperparameter-grid axis)."""

    def collection(self) -> PEARLConfig:
        """Where ``num_trajectories`` and ``budget_for`` are (``jcomps.methods.base.collection``): here."""
        return self

    def __post_init__(self):
        if holds_tracers(self):  # a traced grid value (``numerics.holds_tracers``)
            return
        check_finite_fields(self)
        positive_int = "an integer >= 1"
        for name in ("num_trajectories", "minibatch_size", "meta_batch", "context_size", "latent_size",
                     "buffer_size", "max_tasks"):
            check_field(getattr(self, name) >= 1, name, getattr(self, name), positive_int)
        check_field(self.num_updates is None or self.num_updates >= 1, "num_updates", self.num_updates,
                    "None (updates_per_step × env steps) or an integer >= 1")
        check_field(self.updates_per_step > 0, "updates_per_step", self.updates_per_step, "a number > 0")
        check_field(self.initial_steps >= 0, "initial_steps", self.initial_steps, "an integer >= 0 (0: none)")
        check_field(self.context_source in CONTEXT_SOURCES, "context_source", self.context_source,
                    " or ".join(repr(c) for c in CONTEXT_SOURCES))
        if self.context_source == "prior":
            check_field(0 < self.prior_fraction < 1 and 1 <= self.prior_episodes < self.num_trajectories,
                        "prior_fraction", self.prior_fraction,
                        f"a share in (0, 1) that leaves at least one of the num_trajectories = "
                        f"{self.num_trajectories} episodes to each of the prior and the posterior")
        check_field(0 <= self.current_slots <= self.meta_batch, "current_slots", self.current_slots,
                    f"an integer in [0, meta_batch = {self.meta_batch}]")
        check_field(self.budget is None or self.budget >= 1, "budget", self.budget, "None or an integer >= 1")
        for name in ("hidden_sizes", "encoder_hidden_sizes"):
            sizes = getattr(self, name)
            check_field(len(sizes) >= 1 and all(h >= 1 for h in sizes), name, sizes, "one or more positive widths")
        check_field(self.learning_rate > 0, "learning_rate", self.learning_rate, "a number > 0")
        check_field(0 < self.discount <= 1, "discount", self.discount, "a number in (0, 1]")
        check_field(0 < self.tau <= 1, "tau", self.tau, "a number in (0, 1]")
        check_field(self.reward_scale > 0, "reward_scale", self.reward_scale, "a number > 0")
        check_field(self.kl_weight >= 0, "kl_weight", self.kl_weight, "a number >= 0")
        check_field(self.alpha > 0, "alpha", self.alpha, "a number > 0")
        check_field(self.policy_reg >= 0, "policy_reg", self.policy_reg, "a number >= 0")

    def budget_for(self, family: Family) -> int:
        """Iterations per task for ``family``."""
        return family.default_budget if self.budget is None else self.budget

    @property
    def prior_episodes(self) -> int:
        """Episodes of an iteration collected with z from the prior (``context_source="prior"``)."""
        return int(round(self.prior_fraction * self.num_trajectories))

    def updates_for(self, family: Family) -> int:
        """Gradient steps per iteration on ``family``."""
        if self.num_updates is not None:
            return self.num_updates
        return max(1, int(round(self.updates_per_step * self.num_trajectories * family.max_steps)))

    def follow(self, family: Family, keep: frozenset = frozenset()) -> "PEARLConfig":
        """This config with the fields that follow another value filled, as a run records them
        (``jcomps.methods.with_followed``): ``budget`` None, the family's default budget; ``num_updates`` None,
        ``updates_for(family)``, unless a grid varies what it follows (``keep``: the grid's flat field names)."""
        fill = {"budget": self.budget_for(family)} if self.budget is None else {}
        if self.num_updates is None and not keep & {"updates_per_step", "num_trajectories"}:
            fill["num_updates"] = self.updates_for(family)
        return dataclasses.replace(self, **fill) if fill else self

    def initial_episodes(self, family: Family) -> int:
        """Episodes collected with the prior before a task's first iteration."""
        return -(-self.initial_steps // family.max_steps)


CONTEXT_SOURCES = ("prior", "replay")

class PEARLState(NamedTuple):
    """params: ActorCriticParams(policy={'net': the policy network's parameters, 'z': f32[latent] drawn from the
    posterior of the last task learnt}, value=()); q, target_q: the twin critics and their Polyak averages;
    encoder: the context encoder; policy_opt, critic_opt (critics and encoder), alpha_opt: Adam states;
    log_alpha: f32[]; replay: a TransitionStore per task slot; contexts: the encoder buffers, a TransitionStore per
    task slot holding its last iteration's prior-z episodes (``context_source="prior"``; zero rows with
    ``replay``); rng; task_index: i32[], tasks learnt so far."""

    params: networks.ActorCriticParams
    q: Any
    target_q: Any
    encoder: Any
    policy_opt: Any
    critic_opt: Any
    alpha_opt: Any
    log_alpha: jax.Array
    replay: buffers.TransitionStore
    contexts: buffers.TransitionStore
    rng: jax.Array
    task_index: jax.Array


class Networks(NamedTuple):
    """The static parts: brax's SAC networks (policy and twin critics on [obs, z]) and the encoder MLP."""

    sac: Any
    encoder: Any
    context_size: int


def make_networks(config: PEARLConfig, family: Family) -> Networks:
    """brax's SAC networks on observations extended by z, and the context encoder."""
    sac = sac_networks.make_sac_networks(family.obs_size + config.latent_size, family.action_size,
                                         hidden_layer_sizes=config.hidden_sizes)
    width = 2 * family.obs_size + family.action_size + 1 if config.context_next_obs else (
        family.obs_size + family.action_size + 1)
    encoder = brax_networks.MLP(layer_sizes=(*config.encoder_hidden_sizes, 2 * config.latent_size),
                                activation=jax.nn.relu)
    return Networks(sac, encoder, width)


def with_latent(obs: jax.Array, z: jax.Array) -> jax.Array:
    """[obs, z] over the last axis; z f32[latent] or with leading axes that broadcast against obs's."""
    z = jnp.broadcast_to(z, obs.shape[:-1] + z.shape[-1:])
    return jnp.concatenate([obs, z], axis=-1)


def make_act(nets: Networks):
    """The ``acting.ActFn`` of PEARL's policies ({'net', 'z'}): tanh(loc + scale·noise), and its log-probability
    with the tanh correction (brax's ``NormalTanhDistribution``)."""
    dist = nets.sac.parametric_action_distribution

    def act(policy: dict, obs: jax.Array, noise: jax.Array):
        params = nets.sac.policy_network.apply(None, policy["net"], with_latent(obs, policy["z"]))
        loc, scale = jnp.split(params, 2, axis=-1)
        pre = loc + (jax.nn.softplus(scale) + dist._min_std) * dist._var_scale * noise
        return jnp.tanh(pre), dist.log_prob(params, pre)

    return act


def make_actor(nets: Networks) -> acting.Actor:
    """PEARL's ``acting.Actor``: the ``ActFn`` of ``make_act`` and its NumPy twin (``host_acting.tanh_gaussian``)."""
    return acting.Actor(make_act(nets), host_kind="tanh_gaussian")


def context_features(config: PEARLConfig, rows: dict) -> jax.Array:
    """The encoder's input per transition: [s, a, r] or [s, a, r, s'] (``context_next_obs``)."""
    parts = [rows["obs"], rows["action"], rows["reward"][..., None]]
    if config.context_next_obs:
        parts.append(rows["next_obs"])
    return jnp.concatenate(parts, axis=-1)


def product_of_gaussians(mu: jax.Array, var: jax.Array, mask: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The product of the Gaussian factors N(mu_n, var_n) (f32[n, latent]) of the rows where ``mask`` f32[n] is 1,
    normalised: var = 1 / Σ 1/var_n, mu = var Σ mu_n/var_n. With no row, the prior N(0, I)."""
    precision = mask[:, None] / jnp.maximum(var, 1e-7)
    total = jnp.sum(precision, axis=0)
    any_row = jnp.sum(mask) > 0
    post_var = jnp.where(any_row, 1.0 / jnp.maximum(total, 1e-12), 1.0)
    post_mu = jnp.where(any_row, post_var * jnp.sum(precision * mu, axis=0), 0.0)
    return post_mu, post_var


def posterior(config: PEARLConfig, nets: Networks, encoder_params, context: jax.Array,
              mask: jax.Array) -> tuple[jax.Array, jax.Array]:
    """q(z | c): mean and variance f32[latent] of the product of the encoder's per-transition factors over the
    context f32[n, width] (rows with ``mask`` 0 left out)."""
    out = nets.encoder.apply(encoder_params, context)
    mu, raw = jnp.split(out, 2, axis=-1)
    return product_of_gaussians(mu, jax.nn.softplus(raw), mask)


def kl_to_prior(mu: jax.Array, var: jax.Array) -> jax.Array:
    """KL(N(mu, var) ‖ N(0, I)) summed over the last axis; 0 when the posterior is the prior."""
    return 0.5 * jnp.sum(var + jnp.square(mu) - 1.0 - jnp.log(var), axis=-1)


def polyak(target, online, tau):
    """target ← (1 − τ)·target + τ·online, leaf by leaf."""
    return jax.tree.map(lambda t, o: (1.0 - tau) * t + tau * o, target, online)


def draw_slots(config: PEARLConfig, count: jax.Array, current, rng: jax.Array) -> jax.Array:
    """The ``meta_batch`` task slots of one gradient step, i32[meta_batch]: the first ``current_slots`` are
    ``current`` (the task being learnt), the others drawn uniformly, with replacement, from the slots that hold
    data (``count`` i32[max_tasks] > 0)."""
    seen = count > 0
    slots = jax.random.choice(rng, config.max_tasks, (config.meta_batch,), p=seen / jnp.sum(seen))
    return slots.at[:config.current_slots].set(current)


def sample_context(config: PEARLConfig, replay: buffers.TransitionStore, slot, rng,
                   valid_only: bool = False) -> tuple[jax.Array, jax.Array]:
    """``context_size`` transitions of ``slot`` as the encoder's input f32[n, width] and their mask
    (``valid_only``: drawn among the valid transitions, ``buffers.transitions_sample``)."""
    rows, mask = buffers.transitions_sample(replay, slot, config.context_size, rng, valid_only)
    return context_features(config, rows), mask


def _transitions(obs, action, reward, done, next_obs, mask):
    """A brax Transition of flat rows; rows with ``mask`` 0 are marked truncated (brax's critic loss zeroes
    their error); the time limit itself is never a truncation here: s' at T_max is stored and bootstraps."""
    return brax_types.Transition(observation=obs, action=action, reward=reward, discount=1.0 - done,
                                 next_observation=next_obs,
                                 extras={"state_extras": {"truncation": 1.0 - mask}, "policy_extras": {}})


def critic_objective(config: PEARLConfig, nets: Networks, critic_loss_fn, q_encoder, policy_net, target_q, alpha,
                     rows: dict, mask: jax.Array, contexts: jax.Array, context_mask: jax.Array, key: jax.Array):
    """The critics' and encoder's loss on a meta-batch of M task slots: oyster's Σ_k mean (Q_k(s, a, z) − y)² (brax's
    critic loss, ½ mean over rows and both critics, times 4, over the valid rows) plus ``kl_weight`` · the mean over
    the slots of KL(q(z|c) ‖ N(0, I)) (``PEARLConfig.kl_weight``: oyster's weight per task). ``rows`` hold
    [M, n, ...] transitions with ``mask`` f32[M, n]; ``contexts`` f32[M, c, width] with ``context_mask``. z is
    drawn per slot by reparameterisation, so the encoder learns through Q(s, a, z) (brax's target is under
    stop_gradient) and the KL. Returns (loss, (critic loss, mean KL, z [M, latent]
    with its gradient stopped))."""
    q, encoder = q_encoder
    k_z, k_loss = jax.random.split(key)
    mu, var = jax.vmap(lambda c, m: posterior(config, nets, encoder, c, m))(contexts, context_mask)
    z = mu + jnp.sqrt(var) * jax.random.normal(k_z, mu.shape, jnp.float32)  # [M, latent]
    zs = z[:, None, :]  # one z per task slot, for all its rows
    flat = lambda x: x.reshape((-1,) + x.shape[2:])  # noqa: E731
    trans = _transitions(flat(with_latent(rows["obs"], zs)), flat(rows["action"]), flat(rows["reward"]),
                         flat(rows["done"]), flat(with_latent(rows["next_obs"], zs)), flat(mask))
    rows_total = mask.size
    q_loss = 4.0 * critic_loss_fn(q, policy_net, None, target_q, alpha, trans, k_loss) * rows_total / jnp.maximum(
        jnp.sum(mask), 1.0)
    kl = jnp.mean(kl_to_prior(mu, var))
    return q_loss + config.kl_weight * kl, (q_loss, kl, jax.lax.stop_gradient(z))


critic_grad = jax.value_and_grad(critic_objective, argnums=3, has_aux=True)


def actor_objective(config: PEARLConfig, nets: Networks, policy_net, q, alpha, obs_z: jax.Array, mask: jax.Array,
                    key: jax.Array):
    """brax's actor loss α log π(ã|s, z) − min_k Q_k(s, ã, z), ã ~ π(·|s, z) by reparameterisation, as a mean over
    the valid rows only (brax's is over every row; after a termination a row is no transition), plus oyster's
    regularisers ``policy_reg`` · (mean loc² + mean log-scale²) of the pre-tanh Gaussian. Returns (loss, log π
    f32[n] of the samples, for the temperature and the entropy metric)."""
    dist = nets.sac.parametric_action_distribution
    params = nets.sac.policy_network.apply(None, policy_net, obs_z)
    pre = dist.sample_no_postprocessing(params, key)
    log_prob = dist.log_prob(params, pre)
    q_action = nets.sac.q_network.apply(None, q, obs_z, dist.postprocess(pre))
    per_row = alpha * log_prob - jnp.min(q_action, axis=-1)
    weight = masked_weights(mask)
    loc, raw = jnp.split(params, 2, axis=-1)
    log_scale = jnp.log(jax.nn.softplus(raw) + dist._min_std)
    reg = config.policy_reg * jnp.sum(weight[:, None] * (jnp.square(loc) + jnp.square(log_scale))) / loc.shape[-1]
    return jnp.sum(weight * per_row) + reg, jax.lax.stop_gradient(log_prob)


actor_grad = jax.value_and_grad(actor_objective, argnums=2, has_aux=True)


def alpha_objective(log_alpha, log_prob: jax.Array, mask: jax.Array, target_entropy: float):
    """brax's temperature loss α · (−log π − target entropy), as a mean over the valid rows: α falls while the
    policy's entropy is above the target and rises below it."""
    weight = masked_weights(mask)
    return jnp.sum(weight * jnp.exp(log_alpha) * jax.lax.stop_gradient(-log_prob - target_entropy))


class Setup(NamedTuple):
    """What PEARL's functions share for one family and config, built once by ``setup``; every function below
    takes it first (``make`` binds it)."""

    config: PEARLConfig
    family: Family
    nets: Networks
    actor: acting.Actor
    critic_loss_fn: Any
    """brax's SAC critic loss with this config's reward scale and discount."""
    optimizer: optax.GradientTransformation
    budget: int
    num_updates: int
    """Gradient steps per iteration."""
    capacity: int
    """Transitions per task slot of the replay."""
    n_prior: int
    """Episodes per iteration with z from the prior (``context_source="prior"``; 0 otherwise)."""
    n_initial: int
    """Episodes with z from the prior before a task's first iteration."""
    target_entropy: float

    @property
    def from_prior(self) -> bool:
        return self.config.context_source == "prior"

    @property
    def n_post(self) -> int:
        """Episodes per iteration with z from the posterior."""
        return self.config.num_trajectories - self.n_prior

    @property
    def valid_only(self) -> bool:
        """Where episodes can end early, rows after the end are stored but are no transitions: draw among the
        valid ones, so every slot gets full batches and contexts (oyster stores only the steps taken)."""
        return self.family.can_terminate


def setup(family: Family, config: PEARLConfig) -> Setup:
    nets = make_networks(config, family)
    batch = config.num_trajectories * family.max_steps
    _, critic_loss_fn, _ = sac_losses.make_losses(nets.sac, reward_scaling=config.reward_scale,
                                                  discounting=config.discount, action_size=family.action_size)
    return Setup(config, family, nets, make_actor(nets), critic_loss_fn, optax.adam(config.learning_rate),
                 budget=config.budget_for(family), num_updates=config.updates_for(family),
                 capacity=buffers.transition_capacity(config.buffer_size, batch),
                 n_prior=config.prior_episodes if config.context_source == "prior" else 0,
                 n_initial=config.initial_episodes(family),
                 target_entropy=-0.5 * family.action_size)  # brax's


def init(p: Setup, rng: jax.Array) -> PEARLState:
    config, family = p.config, p.family
    rng, k_pi, k_q, k_enc = jax.random.split(rng, 4)
    policy = {"net": p.nets.sac.policy_network.init(k_pi), "z": jnp.zeros((config.latent_size,), jnp.float32)}
    q = p.nets.sac.q_network.init(k_q)
    encoder = p.nets.encoder.init(k_enc, jnp.zeros((1, p.nets.context_size), jnp.float32))
    log_alpha = jnp.log(jnp.asarray(config.alpha, jnp.float32))
    example = buffers.rollout_example(family, config.num_trajectories)
    replay = buffers.transitions_init_like(example, config.max_tasks, p.capacity)
    contexts = buffers.transitions_init_like(example, config.max_tasks, p.n_prior * family.max_steps)
    return PEARLState(networks.ActorCriticParams(policy, ()), q, q, encoder, p.optimizer.init(policy["net"]),
                      p.optimizer.init((q, encoder)), p.optimizer.init(log_alpha), log_alpha, replay, contexts, rng,
                      jnp.int32(0))


def context_store(p: Setup, state: PEARLState) -> buffers.TransitionStore:
    """The store contexts are drawn from (``context_source``)."""
    return state.contexts if p.from_prior else state.replay


def draw_z(p: Setup, encoder, store: buffers.TransitionStore, slot, rng: jax.Array, shape=()) -> jax.Array:
    """z from the posterior of one context of ``slot``, ``shape`` draws of it."""
    k_ctx, k_z = jax.random.split(rng)
    context, mask = sample_context(p.config, store, slot, k_ctx, p.valid_only)
    mu, var = posterior(p.config, p.nets, encoder, context, mask)
    return mu + jnp.sqrt(var) * jax.random.normal(k_z, shape + mu.shape, jnp.float32)


def prior_z(p: Setup, rng: jax.Array, episodes: int) -> jax.Array:
    return jax.random.normal(rng, (episodes, p.config.latent_size), jnp.float32)


def rollout(p: Setup, state: PEARLState, z: jax.Array, task, rng: jax.Array, episodes: int):
    """``episodes`` episodes on ``task``, episode n acting with z[n]."""
    return acting.rollout(p.family, {**state.params.policy, "z": z}, task, rng, episodes, actor=p.actor)


def collect(p: Setup, state: PEARLState, task, slot, k_z, k_roll):
    """One iteration's episodes and what they change: (state with its buffers written, the episodes that give the
    iteration's success rate and return, whether every episode is finite)."""
    if p.from_prior:  # oyster: prior-z episodes fill the emptied encoder buffer, posterior ones the replay only
        (k_zp, k_ctx), (k_prior, k_post) = jax.random.split(k_z), jax.random.split(k_roll)
        prior = rollout(p, state, prior_z(p, k_zp, p.n_prior), task, k_prior, p.n_prior)
        contexts = buffers.transitions_add(buffers.transitions_clear(state.contexts, slot), slot, prior)
        z = jax.vmap(lambda k: draw_z(p, state.encoder, contexts, slot, k))(jax.random.split(k_ctx, p.n_post))
        post = rollout(p, state, z, task, k_post, p.n_post)
        replay = buffers.transitions_add(buffers.transitions_add(state.replay, slot, prior), slot, post)
        finite = all_finite((prior.obs, prior.reward, post.obs, post.reward))
        return state._replace(replay=replay, contexts=contexts), post, finite
    z = draw_z(p, state.encoder, state.replay, slot, k_z, (p.config.num_trajectories,))
    traj = rollout(p, state, z, task, k_roll, p.config.num_trajectories)
    finite = all_finite((traj.obs, traj.reward))
    return state._replace(replay=buffers.transitions_add(state.replay, slot, traj)), traj, finite


def gradient_step(p: Setup, state: PEARLState, key: jax.Array):
    """One SAC step of critic and encoder, actor and (``auto_alpha``) temperature on ``meta_batch`` task slots:
    (state, its UpdateTerms, whether it was not finite and so not taken)."""
    config = p.config
    k_slots, k_rows, k_ctx, k_critic, k_actor = jax.random.split(key, 5)
    slots = draw_slots(config, state.replay.count, state.task_index, k_slots)
    rows, mask = jax.vmap(lambda s, k: buffers.transitions_sample(state.replay, s, config.minibatch_size, k,
                                                                  p.valid_only))(
        slots, jax.random.split(k_rows, config.meta_batch))
    contexts, context_mask = jax.vmap(lambda s, k: sample_context(config, context_store(p, state), s, k,
                                                                  p.valid_only))(
        slots, jax.random.split(k_ctx, config.meta_batch))
    alpha = jnp.exp(state.log_alpha)
    policy_net = state.params.policy["net"]
    (_, (q_loss, kl, z)), g_critic = critic_grad(config, p.nets, p.critic_loss_fn, (state.q, state.encoder),
                                                 policy_net, state.target_q, alpha, rows, mask, contexts,
                                                 context_mask, k_critic)
    (q, encoder), critic_opt = optimizer_step(p.optimizer, g_critic, state.critic_opt, (state.q, state.encoder))
    obs_z = with_latent(rows["obs"], z[:, None, :]).reshape((-1, p.family.obs_size + config.latent_size))
    flat_mask = mask.reshape(-1)
    (actor_loss, log_prob), g_pi = actor_grad(config, p.nets, policy_net, q, alpha, obs_z, flat_mask, k_actor)
    new_policy_net, policy_opt = optimizer_step(p.optimizer, g_pi, state.policy_opt, policy_net)
    if config.auto_alpha:  # on the actor's samples, before its step (brax's order)
        g_alpha = jax.grad(alpha_objective)(state.log_alpha, log_prob, flat_mask, p.target_entropy)
        log_alpha, alpha_opt = optimizer_step(p.optimizer, g_alpha, state.alpha_opt, state.log_alpha)
    else:
        g_alpha, alpha_opt, log_alpha = jnp.float32(0.0), state.alpha_opt, state.log_alpha
    target_q = polyak(state.target_q, q, config.tau)
    new = state._replace(params=state.params._replace(policy={**state.params.policy, "net": new_policy_net}),
                         q=q, target_q=target_q, encoder=encoder, policy_opt=policy_opt, critic_opt=critic_opt,
                         alpha_opt=alpha_opt, log_alpha=log_alpha)
    terms = rl_loop.UpdateTerms(actor_loss, q_loss, -masked_mean(log_prob, flat_mask), kl, jnp.float32(0.0))
    finite = all_finite((terms, g_alpha, g_critic, g_pi))
    return keep_if_finite(finite, new, state), terms, ~finite


def update(p: Setup, state: PEARLState, _, key: jax.Array):
    """An iteration's ``num_updates`` gradient steps (``rl_loop.iterate``'s update)."""
    def step(carry, key):
        s, bad = carry
        s, terms, nonfinite = gradient_step(p, s, key)
        return (s, bad | nonfinite), terms

    (state, bad), terms = jax.lax.scan(step, (state, jnp.array(False)), jax.random.split(key, p.num_updates))
    return state, rl_loop.mean_terms(terms)._replace(value_ev=jnp.float32(jnp.nan)), bad  # (Q-critics)


def learn_task(p: Setup, progress_fn: Optional[ProgressFn], state: PEARLState, task) -> tuple[PEARLState,
                                                                                             TaskMetrics]:
    slot = state.task_index

    def collect_iteration(state: PEARLState, aux, keys, it):
        state, traj, finite = collect(p, state, task, slot, *keys)
        return state, aux, rl_loop.Collected(None, *rl_loop.episode_stats(p.family, traj), finite)

    if p.n_initial:  # oyster's num_initial_steps, with z from the prior, before the task's first iteration
        rng, k_z, k_roll = jax.random.split(state.rng, 3)
        initial = rollout(p, state, prior_z(p, k_z, p.n_initial), task, k_roll, p.n_initial)
        state = state._replace(replay=buffers.transitions_add(state.replay, slot, initial), rng=rng)
    out = rl_loop.iterate(collect_iteration, functools.partial(update, p), state, state.rng,
                          threshold=p.family.success_threshold, budget=p.budget, collect_keys=2,
                          progress_fn=with_fields(progress_fn, task=state.task_index))
    s = out.state
    rng, k_z = jax.random.split(out.rng)
    z = draw_z(p, s.encoder, context_store(p, s), slot, k_z)
    s = s._replace(params=s.params._replace(policy={**s.params.policy, "z": z}), rng=rng,
                   task_index=state.task_index + 1)
    return s, TaskMetrics(out.iterations, out.solved, out.metrics)


def policy_for(p: Setup, state: PEARLState, slot, task, rng):
    """The policy with z from the posterior of a context of ``slot``'s data (not of ``task``'s)."""
    return {**state.params.policy, "z": draw_z(p, state.encoder, context_store(p, state), slot, rng)}


def adapt(p: Setup, state: PEARLState, task, rng: jax.Array, iterations: int):
    """PEARL's meta-test on ``task``: adaptation by inference, (returns, success rates) f32[iterations]."""
    config, family = p.config, p.family

    def one(carry, key):
        prev, has_prev = carry
        k_ctx, k_z, k_roll = jax.random.split(key, 3)
        idx = jax.random.randint(k_ctx, (config.context_size,), 0, prev["reward"].shape[0])
        rows = jax.tree.map(lambda x: x[idx], prev)
        mask = rows.pop("valid") * has_prev.astype(jnp.float32)
        mu, var = posterior(config, p.nets, state.encoder, context_features(config, rows), mask)
        z = mu + jnp.sqrt(var) * jax.random.normal(k_z, (config.num_trajectories,) + mu.shape, jnp.float32)
        traj = rollout(p, state, z, task, k_roll, config.num_trajectories)
        return (buffers.finite_transitions(traj), jnp.array(True)), rl_loop.episode_stats(family, traj)

    batch = config.num_trajectories * family.max_steps
    z = lambda *shape: jnp.zeros((batch,) + shape, jnp.float32)  # noqa: E731
    empty = {"obs": z(family.obs_size), "action": z(family.action_size), "reward": z(),
             "next_obs": z(family.obs_size), "done": z(), "valid": z()}
    _, (returns, success) = jax.lax.scan(one, (empty, jnp.array(False)), jax.random.split(rng, iterations))
    return returns, success


def make(family: Family, config: PEARLConfig = PEARLConfig(), progress_fn: Optional[ProgressFn] = None) -> Method:
    """PEARL on ``family``: ``init`` and ``learn_task`` as every method (``jcomps.methods.base``), with
    ``policy_for`` and ``adapt``; the functions above bound to one ``Setup``."""
    p = setup(family, config)

    def bind(fn, *args):  # a partial that keeps fn's name and source (chex.assert_max_traces reads them)
        return functools.update_wrapper(functools.partial(fn, *args), fn)

    return Method("pearl", config, family, bind(init, p), bind(learn_task, p, progress_fn),
                  env_steps_before_task=p.n_initial * family.max_steps, actor=p.actor,
                  policy_for=bind(policy_for, p), adapt=bind(adapt, p))
