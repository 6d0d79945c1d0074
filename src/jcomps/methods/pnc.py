"""Progress & Compress (PNC; Schwarz et al. 2018) with PPO as the RL algorithm, as the CoMPS paper compares it.

Two columns, both with hidden layers ``ppo.hidden_sizes`` (paper: [128, 128]):

- the *knowledge base* (KB): a plain Gaussian policy, the consolidated one. ``state.params.policy`` is the KB, so
  backward transfer, held-out adaptation and the next task's laterals all read it.
- the *active column*: a policy whose layers i >= 2 receive layer-wise adaptors from the KB's hidden layer i − 1
  (``column_mean``; PPO, rollouts and the compress phase apply it through ``COLUMN``), and a value network. It is
  re-initialised, adaptors included, at every new task (``reset_active``; Schwarz et al. recommend it for diverse
  tasks, and their Atari ablation keeps transfer only with it) to the initial parameters drawn once per seed by
  ``init``; the observation statistics are data and carry over.

Per task, with budget N and C = ceil(``compress_fraction`` · N) compress iterations:

- **progress**: PPO on the task in the active column (the KB frozen: it gets no gradient, and its parameters are
  restored bit for bit after the step) until the success threshold or N − C iterations: iterations-to-success
  counts this phase (N when the threshold is never reached);
- **compress**: C iterations, each collecting ``ppo.num_trajectories`` episodes with the active column and making
  ``ppo.num_updates`` Adam steps (learning rate ``distill_learning_rate``, minibatches of ``ppo.minibatch_size``
  states) on E_s KL(π_active(·|s) ‖ π_KB(·|s)) + (λ/2) Σ γF*_{k−1} (θ_KB − θ*_{k−1})² (Schwarz et al., eq. 2);
- then the online-EWC statistics: F_k, the diagonal Fisher of the KB policy on the last compress batch's states
  (actions drawn from the KB), normalised by its largest entry; F*_k = γF*_{k−1} + F_k; anchor θ*_k = θ_KB.

The knowledge base's observation statistics (``kb_statistics="tasks"``) are an equal-weight pool of every compressed
task's statistics (each task's from its compress batches), updated before each compress phase distils; the KB's
first layer, the EWC anchor and the Fisher are re-expressed in the new statistics so that the KB computes the same
function on the states behind the old ones (``renormalise``). docs/design.md ("Progress & Compress") has why.
"""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar, NamedTuple, Optional, Sequence

import jax
import jax.numpy as jnp
import optax

from jcomps import progress
from jcomps.envs.base import Family
from jcomps.methods.base import Method, TaskMetrics
from jcomps.numerics import (
    check_field, check_finite_fields, guarded_update, holds_tracers, masked_mean, masked_weights,
)
from jcomps.progress import ProgressFn, with_fields
from jcomps.training import acting, networks, ppo

KB_STATISTICS = ("tasks", "first_task")
"""The choices of ``PNCConfig.kb_statistics``."""


@dataclasses.dataclass(frozen=True)
class PNCConfig(ppo.PPOBased):
    """Configuration of Progress & Compress."""

    ppo: ppo.PPOConfig = ppo.PPOConfig(hidden_sizes=(128, 128))
    """The progress phase's PPO (hidden sizes of both columns); ``num_trajectories``, ``num_updates`` and
    ``minibatch_size`` also shape the compress phase."""
    compress_fraction: float = 0.05
    """Share of the task's budget spent on the compress phase (paper: the last 5%)."""
    distill_learning_rate: float = 1e-3
    """Adam learning rate of the knowledge base during the compress phase."""
    ewc_lambda: float = 25.0
    """λ, weight of the online-EWC penalty (Schwarz et al. searched 25, 75, 125, 175 in their RL experiments)."""
    ewc_gamma: float = 0.99
    """γ, decay of the running Fisher F* (Schwarz et al.'s choice on Omniglot; γ < 1)."""
    fisher_states: int = 1024
    """States (of the last compress batch) that estimate the diagonal Fisher of the knowledge base."""
    reset_active: bool = True
    """Re-initialise the active column and its adaptors at every new task (Schwarz et al.'s recommendation)."""
    kb_statistics: str = "tasks"
    """The knowledge base's observation statistics: ``tasks``, pooled over every compressed task with equal weight
    (updated at each compress phase, the KB's first layer re-expressed to keep its function on earlier tasks);
    ``first_task``, the active column's at the first compress phase, then kept (an ablation:
    on MetaWorld, P-0's constant dimensions clip Hammer's observations at ±OBS_CLIP)."""

    TRACED: ClassVar[frozenset] = frozenset({"distill_learning_rate", "ewc_lambda", "ewc_gamma"})
    """Fields that may hold traced scalars (a hyperparameter-grid axis)."""

    def __post_init__(self):
        if holds_tracers(self):  # a traced grid value (``numerics.holds_tracers``)
            return
        check_finite_fields(self)
        check_field(0 < self.compress_fraction < 1, "compress_fraction", self.compress_fraction,
                    "a number in (0, 1)")
        check_field(self.distill_learning_rate > 0, "distill_learning_rate", self.distill_learning_rate,
                    "a number > 0")
        check_field(self.ewc_lambda >= 0, "ewc_lambda", self.ewc_lambda, "a number >= 0")
        check_field(0 <= self.ewc_gamma <= 1, "ewc_gamma", self.ewc_gamma, "a number in [0, 1]")
        check_field(self.fisher_states >= 1, "fisher_states", self.fisher_states, "an integer >= 1")
        check_field(self.kb_statistics in KB_STATISTICS, "kb_statistics", self.kb_statistics,
                    ", ".join(KB_STATISTICS))


def adaptors_init(rng: jax.Array, sizes: Sequence[int]) -> list[dict]:
    """Layer-wise adaptors of an active column whose layers are ``sizes[0] -> ... -> sizes[-1]``: one for every
    layer i >= 2 (its input from the knowledge base is the KB's hidden layer i − 1, of width ``sizes[i - 1]``).

    Adaptor i (Schwarz et al. 2018, eq. 1, after Rusu et al. 2016): ``α_i ⊙ U_i tanh(V_i h^KB_{i−1} + c_i)``, an MLP
    with one hidden layer as wide as its input, and a trainable scale vector α_i ~ U(0, 0.1) of layer i's width.
    """
    out = []
    for i in range(1, len(sizes) - 1):
        n_in, n_out = sizes[i], sizes[i + 1]
        kv, ku, ka = jax.random.split(jax.random.fold_in(rng, i), 3)
        out.append({
            "v": jax.nn.initializers.orthogonal(math.sqrt(2.0))(kv, (n_in, n_in), jnp.float32),
            "c": jnp.zeros((n_in,), jnp.float32),
            "u": jax.nn.initializers.orthogonal(1.0)(ku, (n_in, n_out), jnp.float32),
            "alpha": jax.random.uniform(ka, (n_out,), jnp.float32, 0.0, 0.1),
        })
    return out


def kb_features(kb: dict, obs: jax.Array) -> list[jax.Array]:
    """The hidden activations h^KB_1 … h^KB_{L−1} of the knowledge base's mean MLP at raw ``obs`` (its own
    observation statistics), with no gradient into the knowledge base."""
    kb = jax.lax.stop_gradient(kb)
    h = networks.normalize_obs(kb, obs)
    feats = []
    for layer in kb["mean"][:-1]:
        h = jnp.tanh(h @ layer["w"] + layer["b"])
        feats.append(h)
    return feats


def column_layers(policy: dict, obs: jax.Array) -> tuple[list[jax.Array], jax.Array]:
    """The hidden activations [f32[..., width] per hidden layer] and the action mean f32[..., A] of an active column
    at raw ``obs``: ``policy['mean']`` layers, with adaptor i adding ``α_i ⊙ U_i tanh(V_i h^KB_{i−1} + c_i)`` to layer
    i's pre-activation (i >= 2; the last layer is linear).

    ``policy['kb']`` (the frozen knowledge base, a plain policy) gets no gradient: the lateral connections carry
    gradient into the active column and its adaptors only.
    """
    lead = obs.shape[:-1]
    obs = obs.reshape((-1, obs.shape[-1]))
    feats = kb_features(policy["kb"], obs)
    h = networks.normalize_obs(policy, obs)
    layers, hidden = policy["mean"], []
    for i, layer in enumerate(layers):
        pre = h @ layer["w"] + layer["b"]
        if i >= 1:
            a = policy["adaptors"][i - 1]
            pre = pre + a["alpha"] * (jnp.tanh(feats[i - 1] @ a["v"] + a["c"]) @ a["u"])
        h = pre if i == len(layers) - 1 else jnp.tanh(pre)
        if i < len(layers) - 1:
            hidden.append(h.reshape(lead + h.shape[-1:]))
    return hidden, h.reshape(lead + h.shape[-1:])


def column_mean(policy: dict, obs: jax.Array) -> jax.Array:
    """Action mean f32[..., A] of an active column (``column_layers``)."""
    return column_layers(policy, obs)[1]


def column_hidden(policy: dict, obs: jax.Array) -> list[jax.Array]:
    """The hidden activations of an active column (``column_layers``)."""
    return column_layers(policy, obs)[0]


def column_dist(policy: dict, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Mean f32[..., A] (``column_mean``) and log-std f32[A] of an active column at (raw) ``obs``."""
    return column_mean(policy, obs), policy["log_std"]


COLUMN = networks.PolicyFns(column_dist, host_kind="pnc_column", hidden=column_hidden)
"""How an active column (``with_kb``) is applied; its NumPy twin is ``jcomps.envs.host_acting.pnc_column``."""


class PNCState(NamedTuple):
    """params: ActorCriticParams (policy: the knowledge base; value: the active column's value network);
    active: the active column's policy (layers, log-std, observation statistics, adaptors; no ``kb`` entry);
    fresh: the active column's initial policy and value network (``reset_active`` restores them at every new task);
    fisher: F*, the running Fisher over the KB's trainable leaves; anchor: θ*_{k−1}; rng; task_index: i32[]."""

    params: networks.ActorCriticParams
    active: dict
    fresh: networks.ActorCriticParams
    fisher: dict
    anchor: dict
    rng: jax.Array
    task_index: jax.Array


def compress_iterations(config: PNCConfig, budget: int) -> int:
    """C = ceil(compress_fraction · budget), at least 1 and at most budget − 1."""
    return min(max(1, math.ceil(config.compress_fraction * budget)), budget - 1)


def trainable(policy: dict) -> dict:
    """The leaves of a plain policy that learn (the mean MLP and the log-std; not the observation statistics)."""
    return {"mean": policy["mean"], "log_std": policy["log_std"]}


def init_active(config: PNCConfig, family: Family, rng: jax.Array, obs_norm) -> tuple[dict, list]:
    """A fresh active column (policy with adaptors, value network) keeping the observation statistics."""
    k_ac, k_ad = jax.random.split(rng)
    fresh = ppo.init_params(config.ppo, family, k_ac)
    sizes = (family.obs_size, *config.ppo.hidden_sizes, family.action_size)
    policy = {**fresh.policy, "obs_norm": obs_norm, "adaptors": adaptors_init(k_ad, sizes)}
    return policy, fresh.value


def with_kb(active: dict, kb: dict) -> dict:
    """The active column's policy as it acts: its own parameters with the knowledge base attached."""
    return {**active, "kb": kb}


def gaussian_kl(mean_p, log_std_p, mean_q, log_std_q):
    """KL(N(mean_p, σ_p²) ‖ N(mean_q, σ_q²)) summed over the last (action) axis."""
    var_p, var_q = jnp.exp(2 * log_std_p), jnp.exp(2 * log_std_q)
    return jnp.sum(log_std_q - log_std_p + (var_p + jnp.square(mean_p - mean_q)) / (2 * var_q) - 0.5, axis=-1)


def ewc_penalty(config: PNCConfig, kb_trainable: dict, anchor: dict, fisher: dict):
    """(λ/2) Σ γF* (θ − θ*)²: zero at the anchor, growing with the distance, weighted by the Fisher."""
    terms = jax.tree.map(lambda p, a, f: jnp.sum(config.ewc_gamma * f * jnp.square(p - a)), kb_trainable, anchor,
                         fisher)
    return 0.5 * config.ewc_lambda * sum(jax.tree.leaves(terms))


def distill_loss(config: PNCConfig, kb_trainable: dict, kb: dict, teacher_mean, teacher_log_std, obs, valid,
                 anchor: dict, fisher: dict):
    """Mean KL(π_active ‖ π_KB) over the valid states ``obs`` (the teacher's mean and log-std are constants) plus
    the online-EWC penalty; returns (loss, KL)."""
    student = config.ppo.trained({**kb, **kb_trainable})
    mean, log_std = networks.policy_dist(student, obs)
    kl = gaussian_kl(jax.lax.stop_gradient(teacher_mean), jax.lax.stop_gradient(teacher_log_std), mean, log_std)
    kl = masked_mean(kl, valid)
    return kl + ewc_penalty(config, kb_trainable, anchor, fisher), kl


def diagonal_fisher(kb: dict, obs: jax.Array, valid: jax.Array, rng: jax.Array) -> dict:
    """E_s E_{a~π_KB(·|s)} (∇ log π_KB(a|s))² over the trainable leaves, on the valid rows of ``obs`` f32[n, obs],
    normalised by its largest entry (Schwarz et al. normalise each task's Fisher)."""
    mean, log_std = networks.policy_dist(kb, obs)
    actions = mean + jnp.exp(log_std) * jax.random.normal(rng, mean.shape)
    actions = jax.lax.stop_gradient(actions)

    def score(o, a):
        return jax.grad(lambda t: networks.GAUSSIAN.log_prob({**kb, **t}, o, a))(trainable(kb))

    grads = jax.vmap(score)(obs, actions)
    w = masked_weights(valid)
    fisher = jax.tree.map(lambda g: jnp.tensordot(w, jnp.square(g), axes=1), grads)
    top = jnp.max(jnp.stack([jnp.max(f) for f in jax.tree.leaves(fisher)]))
    return jax.tree.map(lambda f: f / jnp.maximum(top, 1e-12), fisher)


def task_statistics(obs: jax.Array, valid: jax.Array) -> networks.ObsNorm:
    """The mean and variance of the valid rows of ``obs`` f32[..., obs_size] (``valid`` f32[...]); count: their
    number."""
    return networks.obs_norm_update(networks.obs_norm_init(obs.shape[-1]), obs, valid)


def pool_statistics(pooled: networks.ObsNorm, task: networks.ObsNorm, weight) -> networks.ObsNorm:
    """``pooled`` with one more task's statistics merged in at count ``weight``: when every task is merged at the
    same weight, the mean and variance of the equal-weight mixture of the tasks' state distributions (a task solved
    in 3 iterations counts as much as one that took 500). A pool with count 0 becomes ``task``'s statistics."""
    total = pooled.count + weight
    frac = weight / jnp.maximum(total, 1e-12)
    delta = task.mean - pooled.mean
    mean = pooled.mean + frac * delta
    var = (1.0 - frac) * pooled.var + frac * task.var + frac * (1.0 - frac) * jnp.square(delta)
    return networks.ObsNorm(mean, var, total)


def renormalise(kb: dict, anchor: dict, fisher: dict, norm: networks.ObsNorm) -> tuple[dict, dict, dict]:
    """The knowledge base with observation statistics ``norm``, and the EWC anchor and Fisher to match.

    The first layer's pre-activation ``W^T (x − m)/s + b`` becomes ``W'^T (x − m')/s' + b'`` with, per observation
    dimension d, ``W'_d = r_d W_d`` and ``b' = b + Σ_d W'_d (m'_d − m_d)/s'_d``: for r_d = s'_d/s_d this is the same
    function of x (where neither normalisation clips). A dimension whose old standard deviation was at the floor
    (constant in every state behind the old statistics) keeps r_d = 1: its old states all sit at m_d, where the
    bias term alone keeps the function, and scaling its row by s'_d/OBS_STD_MIN would carry the floor's
    amplification into the weights. The anchor θ* is re-expressed the same way (it is the same function too); the
    diagonal Fisher of a scaled row is divided by r_d² (the gradient wrt W'_d is the old one over r_d, less a
    bias-coupling term from the mean shift that a diagonal Fisher cannot hold; the biases' entries are kept).
    A fresh knowledge base (count 0: the untrained initial network, identity statistics) just takes ``norm``."""
    old = kb["obs_norm"]
    seen = old.count > 0
    old_std = jnp.maximum(jnp.sqrt(old.var), networks.OBS_STD_MIN)
    new_std = jnp.maximum(jnp.sqrt(norm.var), networks.OBS_STD_MIN)
    ratio = jnp.where(seen & (jnp.sqrt(old.var) > networks.OBS_STD_MIN), new_std / old_std, 1.0)
    shift = jnp.where(seen, (norm.mean - old.mean) / new_std, 0.0)

    def first_layer(tree):
        layer = tree["mean"][0]
        w = layer["w"] * ratio[:, None]
        return {**tree, "mean": [{"w": w, "b": layer["b"] + shift @ w}, *tree["mean"][1:]]}

    layer = fisher["mean"][0]
    fisher = {**fisher, "mean": [{**layer, "w": layer["w"] / jnp.square(ratio)[:, None]}, *fisher["mean"][1:]]}
    return {**first_layer(kb), "obs_norm": norm}, first_layer(anchor), fisher


def compress(config: PNCConfig, family: Family, kb: dict, active: dict, task, fisher: dict, anchor: dict,
             rng: jax.Array, iterations: int, progress_fn: Optional[ProgressFn] = None):
    """The compress phase: ``iterations`` on-policy batches from the active column, each followed by
    ``num_updates`` Adam steps distilling it into the knowledge base under the EWC penalty; then the online-EWC
    update. Returns (kb, fisher F*_k, anchor θ*_k, KL f32[iterations]: on each iteration's first minibatch, before
    its steps, nonfinite f32[]: 1 if a step was skipped for a NaN or infinity).

    The teacher is fixed through the phase, so its ``iterations`` batches are collected first; with
    ``kb_statistics="tasks"`` their statistics join the knowledge base's pool (each task at the weight of one
    compress phase's samples) and ``renormalise`` re-expresses the KB, the anchor and the Fisher before any
    step, so the KB distils under the statistics it is evaluated with. ``first_task``: the KB takes the active
    column's statistics at its first compress phase and keeps them."""
    pcfg = config.ppo
    optimizer = optax.adam(config.distill_learning_rate)
    acting_policy = with_kb(active, kb)  # the teacher, fixed through the phase (its laterals read this KB)
    grad_fn = jax.value_and_grad(distill_loss, argnums=1, has_aux=True)
    keys = jax.random.split(rng, iterations + 2)
    k_roll, k_perm = jnp.moveaxis(jax.vmap(jax.random.split)(keys[:-2]), 1, 0)

    def collect(_, key):
        traj = acting.rollout(family, acting_policy, task, key, pcfg.num_trajectories, acting.actor_of(COLUMN))
        return None, (traj.obs.reshape((-1, traj.obs.shape[-1])), traj.valid.reshape(-1))

    _, (obs, valid) = jax.lax.scan(collect, None, k_roll)
    if config.kb_statistics == "tasks":
        weight = float(iterations * pcfg.num_trajectories * family.max_steps)
        norm = pool_statistics(kb["obs_norm"], task_statistics(obs, valid), weight)
        kb, anchor, fisher = renormalise(kb, anchor, fisher, norm)
    else:
        fresh = kb["obs_norm"].count <= 0
        kb = {**kb, "obs_norm": jax.tree.map(lambda a, k: jnp.where(fresh, a, k), active["obs_norm"],
                                             kb["obs_norm"])}

    def one_iteration(carry, xs):
        theta, opt_state, bad = carry
        obs, valid, key, it = xs
        t_mean, t_log_std = COLUMN.dist(acting_policy, obs)
        indices = ppo.minibatch_indices(pcfg, obs.shape[0], key)

        def step(carry, idx):
            theta, opt_state, bad = carry
            (loss, kl), g = grad_fn(config, theta, kb, t_mean[idx], t_log_std, obs[idx], valid[idx], anchor, fisher)
            theta, opt_state, finite = guarded_update(optimizer, g, opt_state, theta, loss)
            return (theta, opt_state, bad | ~finite), kl

        (theta, opt_state, bad), kls = jax.lax.scan(step, (theta, opt_state, bad), indices)
        if progress_fn is not None:
            progress_fn({"phase": progress.COMPRESS_ITERATION, "compress_iteration": it + 1,
                         "compress_iterations": jnp.int32(iterations), "kl": kls[0]})
        return (theta, opt_state, bad), kls[0]

    theta0 = trainable(kb)
    init = (theta0, optimizer.init(theta0), jnp.array(False))
    (theta, _, bad), kls = jax.lax.scan(one_iteration, init,
                                        (obs, valid, k_perm, jnp.arange(iterations, dtype=jnp.int32)))
    kb = {**kb, **theta}
    last_obs, last_valid = obs[-1], valid[-1]
    n = min(config.fisher_states, last_obs.shape[0])
    pick = jax.random.choice(keys[-2], last_obs.shape[0], (n,), replace=False)
    new_fisher = diagonal_fisher(kb, last_obs[pick], last_valid[pick], keys[-1])
    fisher = jax.tree.map(lambda old, f: config.ewc_gamma * old + f, fisher, new_fisher)
    return kb, fisher, trainable(kb), kls, bad.astype(jnp.float32)


def make(family: Family, config: PNCConfig = PNCConfig(), progress_fn: Optional[ProgressFn] = None) -> Method:
    pcfg = config.ppo
    budget = pcfg.budget_for(family)
    check_field(budget >= 2, "ppo.budget", budget, "an integer >= 2 for pnc (progress and compress iterations)")
    n_compress = compress_iterations(config, budget)
    n_progress = budget - n_compress
    optimizer = ppo.make_optimizer(pcfg)

    def init(rng: jax.Array) -> PNCState:
        rng, k_kb, k_active = jax.random.split(rng, 3)
        kb = ppo.init_params(pcfg, family, k_kb).policy
        active, value = init_active(config, family, k_active, kb["obs_norm"])
        zeros = jax.tree.map(jnp.zeros_like, trainable(kb))
        return PNCState(networks.ActorCriticParams(kb, value), active, networks.ActorCriticParams(active, value),
                        zeros, trainable(kb), rng, jnp.int32(0))

    def learn_task(state: PNCState, task) -> tuple[PNCState, TaskMetrics]:
        rng, k_rl, k_compress = jax.random.split(state.rng, 3)
        kb = state.params.policy
        if config.reset_active:
            # The initial parameters, not a fresh draw: an orthogonal draw here would run batched QR kernels inside
            # the vmapped program, which can deadlock XLA:CPU's thread pool (jcomps.runner.hostdevices; it hung a
            # study).
            active = {**state.fresh.policy, "obs_norm": state.active["obs_norm"]}
            value = state.fresh.value
        else:
            active, value = state.active, state.params.value
        active = pcfg.task_start(active)
        params = networks.ActorCriticParams(with_kb(active, kb), value)
        report = with_fields(progress_fn, task=state.task_index)
        out = ppo.rl_step(pcfg, family, params, optimizer.init(params), task, k_rl, progress_fn=report,
                          budget=n_progress, policy_fns=COLUMN)
        active = {k: v for k, v in out.params.policy.items() if k != "kb"}  # the KB is frozen: keep it exactly
        kb, fisher, anchor, _, bad = compress(config, family, kb, active, task, state.fisher, state.anchor,
                                              k_compress, n_compress, progress_fn=report)
        pad = lambda x: jnp.concatenate([x, jnp.zeros((n_compress,), x.dtype)])  # noqa: E731
        metrics = jax.tree.map(pad, out.metrics)
        # A skipped compress step is flagged on the task's last progress iteration (the runner reports it).
        last = out.iterations - 1
        metrics = metrics._replace(nonfinite=metrics.nonfinite.at[last].max(bad))
        iterations = jnp.where(out.solved, out.iterations, budget)
        new = PNCState(networks.ActorCriticParams(kb, out.params.value), active, state.fresh, fisher, anchor, rng,
                       state.task_index + 1)
        return new, TaskMetrics(iterations, out.solved, metrics, policy_health=out.health)

    # The compress phase's batches come after the threshold is met: charged to every solved task's samples.
    return Method("pnc", config, family, init, learn_task,
                  env_steps_per_task=n_compress * pcfg.num_trajectories * family.max_steps)
