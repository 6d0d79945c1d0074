"""CoMPS (Continual Meta Policy Search) and the rungs of its ablation ladder (``jcomps.methods``).

Per task i: the RL step (PPO from θ_i) while the experience stores are filled (D*_i: top-20 trajectories by
return, kept incrementally; D_i: 100 trajectories from the last ⌈0.05·N⌉ iterations with behaviour
log-probabilities); then the meta step over every seen task j ≤ i, warm-started (FTML) from the policy that just
finished task i (the ladder's rungs without FTML: from a fresh initialisation, or the last meta policy,
``CoMPSConfig.meta_start``); θ_{i+1} is its result. Task i's value head starts from the RL step's value
function, and the meta step's V-trace runs in the RL step's reward units (``meta.MetaConfig.value_init``,
``reward_scale``).
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp

from jcomps.envs.base import Family
from jcomps.methods.base import Method, TaskMetrics
from jcomps.numerics import check_field, check_finite_fields, concrete_max
from jcomps.progress import ProgressFn, with_fields
from jcomps.training import buffers, meta, networks, ppo

META_STARTS = ("fresh", "last")
WARM_START_STDS = ("learnt", "meta")
FRESH_STREAM = 43
"""``fold_in`` data of the key stream the fresh initialisations are drawn from (any constant: it only has to keep
that stream apart from the splits of the seed's key)."""


@dataclasses.dataclass(frozen=True)
class CoMPSConfig(ppo.PPOBased):
    """Configuration of CoMPS."""

    ppo: ppo.PPOConfig = ppo.PPOConfig()
    """The RL step's hyperparameters."""
    meta: meta.MetaConfig = meta.MetaConfig()
    """The meta step's hyperparameters."""
    max_tasks: int = 40
    """Task slots in the experience stores: at least the sequence length."""
    num_skilled: int = 20
    """|D*_i|, highest-return trajectories kept per task (paper: 20; 40 is the 'skilled data x2' ablation)."""
    num_offpolicy: int = 100
    """|D_i|, trajectories sampled from the last iterations (paper: 100)."""
    recent_fraction: float = 0.05
    """D_i comes from the last min(M, ceil(recent_fraction * N)) iterations (paper: 0.05)."""
    warm_start: bool = True
    """Start each meta step from the policy that just finished the task (FTML); off: from ``meta_start``."""
    warm_start_std: str = "learnt"
    """With the warm start, where the meta step's starting exploration std comes from: ``learnt``, the policy that
    has just learnt the task (the paper's FTML: the whole policy); ``meta``, the last meta policy (the mean
    warm-started, the std as the last meta step left it: a diagnostic that separates what FTML carries in the
    mean from the narrower std PPO has reached). Ignored without the warm start."""
    meta_start: str = "fresh"
    """Where the meta step starts when ``warm_start`` is off: ``fresh``, a fresh initialisation of the policy after
    every task (the family's initialiser, a key of its own per task slot: GMPS as an offline meta-learner trained
    from an initialisation, as the authors' continual prototype restarted it); ``last``, the last meta policy
    (a stronger baseline than the paper's: the next RL step started there, so it is close to the FTML start).
    Either way with the newest observation statistics. Ignored with ``warm_start``."""
    reset_optimizer: bool = True
    """Start each task's RL step with a fresh PPO Adam state."""

    def __post_init__(self):
        check_finite_fields(self)
        check_field(self.max_tasks >= 1, "max_tasks", self.max_tasks, "an integer >= 1")
        check_field(self.num_skilled >= 1, "num_skilled", self.num_skilled, "an integer >= 1")
        check_field(self.num_offpolicy >= 1, "num_offpolicy", self.num_offpolicy, "an integer >= 1")
        check_field(0 < self.recent_fraction <= 1, "recent_fraction", self.recent_fraction, "a number in (0, 1]")
        check_field(self.meta_start in META_STARTS, "meta_start", self.meta_start, ", ".join(META_STARTS))
        check_field(self.warm_start_std in WARM_START_STDS, "warm_start_std", self.warm_start_std,
                    ", ".join(WARM_START_STDS))

    def fresh_start(self) -> bool:
        """Whether the meta step starts from a fresh initialisation after every task."""
        return not self.warm_start and self.meta_start == "fresh"

    def follow(self, family, keep: frozenset = frozenset()) -> "CoMPSConfig":
        """This config with the meta step's fields that follow the RL step filled (``meta_config``), as a run
        records them (``jcomps.methods.with_followed``), but for those following a field a grid varies (``keep``:
        the grid's flat field names; ``meta_config`` fills them at each grid point)."""
        return dataclasses.replace(self, meta=_followed_meta(self, keep))


class CoMPSState(NamedTuple):
    """Everything CoMPS carries between tasks.

    params: PPO actor-critic (policy = θ_i); opt_state: PPO Adam; meta: MetaState (meta policy, per-task value
    heads, Adam states); stores: SequenceStores; rng; task_index: i32[]; fresh: with ``meta_start="fresh"`` (and no
    warm start), the fresh policy initialisations the meta step starts from, one per task slot (leading axis
    [max_tasks]), else None.
    """

    params: networks.ActorCriticParams
    opt_state: Any
    meta: meta.MetaState
    stores: buffers.SequenceStores
    rng: jax.Array
    task_index: jax.Array
    fresh: Optional[dict] = None


# The meta step's fields that follow the RL step's when None: field -> (the RL step's field it follows, its value).
_META_FOLLOWS = {"reward_scale": ("reward_scale", lambda ppo_config: ppo_config.reward_scale),
                 "value_learning_rate": ("learning_rate", lambda ppo_config: ppo_config.learning_rate),
                 "hold_std": ("std_mode", lambda ppo_config: ppo_config.std_mode == "fixed")}


def _followed_meta(config: CoMPSConfig, keep: frozenset = frozenset()) -> meta.MetaConfig:
    fill = {name: value(config.ppo) for name, (source, value) in _META_FOLLOWS.items()
            if getattr(config.meta, name) is None and source not in keep}
    return dataclasses.replace(config.meta, **fill)


def meta_config(config: CoMPSConfig) -> meta.MetaConfig:
    """The meta step's config with the fields that follow the RL step resolved: ``reward_scale`` None takes the RL
    step's reward scale, ``value_learning_rate`` None its learning rate (either may be a traced grid value),
    ``hold_std`` None holds the std where the RL step's is fixed (``ppo.std_mode``). A run's configs come with them
    filled (``CoMPSConfig.follow``) but where a grid varies what they follow: here they take each point's value."""
    return _followed_meta(config)


def meta_start(config: CoMPSConfig, state: CoMPSState, learnt: dict) -> dict:
    """The policy the meta step after a task starts from: with the warm start (FTML), ``learnt``, the policy that
    has just learnt the task; else the task slot's fresh initialisation (``meta_start="fresh"``) or the last meta
    policy (``"last"``), either with ``learnt``'s observation statistics (they describe the data the policy will
    see, not a learnt quantity) and its meta-learnt inner step sizes (``meta.with_inner_step_sizes``: they belong
    to the meta-learner, not to an initialisation). With the warm start and ``warm_start_std="meta"``, ``learnt``
    with the last meta policy's std."""
    if config.warm_start:
        if config.warm_start_std == "meta":
            return {**learnt, "log_std": state.meta.policy["log_std"]}
        return learnt
    if config.fresh_start():
        base = jax.tree.map(lambda x: jax.lax.dynamic_index_in_dim(x, state.task_index, keepdims=False), state.fresh)
    else:
        base = state.meta.policy
    return {**base, **{k: learnt[k] for k in ("obs_norm", "inner_lr") if k in learnt}}


def make(family: Family, config: CoMPSConfig = CoMPSConfig(), progress_fn: Optional[ProgressFn] = None,
         name: str = "comps") -> Method:
    optimizer = ppo.make_optimizer(config.ppo)
    mconfig = meta_config(config)
    policy_opt, value_opt = meta.optimizers(mconfig)
    budget = config.ppo.budget_for(family)
    capacity = buffers.recent_capacity(budget, config.recent_fraction)
    B = config.ppo.num_trajectories

    def init(rng: jax.Array) -> CoMPSState:
        k_fresh = rng
        rng, k_ac, k_v = jax.random.split(rng, 3)
        params = ppo.init_params(config.ppo, family, k_ac)
        params = params._replace(policy=meta.with_inner_step_sizes(mconfig, params.policy))
        value = meta.init_value_heads(k_v, family.obs_size, config.ppo.hidden_sizes, config.max_tasks)
        meta_state = meta.MetaState(params.policy, value, policy_opt.init(params.policy), value_opt.init(value))
        stores = buffers.sequence_init_like(buffers.rollout_example(family, B), config.max_tasks,
                                            config.num_skilled, config.num_offpolicy)
        fresh = None
        if config.fresh_start():
            # Drawn here, one slot at a time (lax.map), not per task inside the vmapped program: a batched QR in the
            # orthogonal initialiser can deadlock XLA:CPU's pool (continual.init_seeds). From a stream folded out
            # of the seed's key, so every other key is the same as the other rungs' (task 1 is the same PPO run).
            fresh = jax.lax.map(lambda k: ppo.init_params(config.ppo, family, k).policy,
                                jax.random.split(jax.random.fold_in(k_fresh, FRESH_STREAM), config.max_tasks))
        return CoMPSState(params, optimizer.init(params), meta_state, stores, rng, jnp.int32(0), fresh)

    def observe(aux, traj, iteration):
        del iteration
        skilled, recent = aux
        return buffers.skilled_update(skilled, traj), buffers.recent_add(recent, traj)

    def learn_task(state: CoMPSState, task) -> tuple[CoMPSState, TaskMetrics]:
        index = concrete_max(state.task_index)
        if index is not None and index >= config.max_tasks:
            raise ValueError(f"{name}: task {index + 1} is past max_tasks={config.max_tasks} (one experience slot "
                             "per task); make the method with more")
        rng, k_rl, k_off, k_meta = jax.random.split(state.rng, 4)
        opt_state = optimizer.init(state.params) if config.reset_optimizer else state.opt_state
        example = buffers.rollout_example(family, B)  # one iteration's batch, shapes only
        aux0 = (buffers.skilled_init_like(example, config.num_skilled), buffers.recent_init_like(example, capacity))
        report = with_fields(progress_fn, task=state.task_index)
        params = state.params._replace(policy=config.ppo.task_start(state.params.policy))
        out = ppo.rl_step(config.ppo, family, params, opt_state, task, k_rl, observe=observe, aux=aux0,
                          progress_fn=report)
        skilled, recent = out.aux
        offpolicy = buffers.sample_offpolicy(recent, config.num_offpolicy, k_off)
        stores = buffers.sequence_write(state.stores, state.task_index, skilled, offpolicy)
        meta_state = state.meta._replace(policy=meta_start(config, state, out.params.policy))
        if mconfig.value_init == "rl_step":  # the RL step's critic has just been fitted to the data D_i holds
            meta_state = meta_state._replace(value=meta.set_head(meta_state.value, state.task_index,
                                                                 out.params.value))
        new_off = jax.tree.map(lambda x: x[state.task_index], stores.offpolicy)
        meta_state = meta_state._replace(value=meta.fit_head(mconfig, meta_state.policy, meta_state.value,
                                                             state.task_index, new_off))
        before = meta.slot_diagnostics(mconfig, meta_state.policy, meta_state.value, stores)
        meta_state, steps = meta.meta_train(mconfig, meta_state, stores, k_meta, progress_fn=report)
        after = meta.slot_diagnostics(mconfig, meta_state.policy, meta_state.value, stores)
        params = out.params._replace(policy=meta_state.policy)
        new = CoMPSState(params, out.opt_state, meta_state, stores, rng, state.task_index + 1, state.fresh)
        return new, TaskMetrics(out.iterations, out.solved, out.metrics, meta.MetaMetrics(steps, before, after),
                                out.health)

    return Method(name, config, family, init, learn_task)


def named(name: str):
    """CoMPS's constructor under another registry name (the rungs of the ablation ladder differ in config only)."""
    def make_named(family: Family, config: CoMPSConfig = CoMPSConfig(), progress_fn: Optional[ProgressFn] = None):
        return make(family, config, progress_fn, name=name)

    return make_named
