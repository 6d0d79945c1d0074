"""PPO+TL: PPO on each task, parameters carried to the next task, no meta step (the paper's baseline); and PPO
from scratch: every task starts from the random initialisation (the single-task reference the paper tunes PPO
on)."""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple, Optional

import jax

from jcomps.envs.base import Family
from jcomps.methods.base import Method, TaskMetrics
from jcomps.progress import ProgressFn, with_fields
from jcomps.training import networks, ppo


@dataclasses.dataclass(frozen=True)
class PPOTLConfig(ppo.PPOBased):
    """Configuration of PPO+TL."""

    ppo: ppo.PPOConfig = ppo.PPOConfig()
    """The RL step's hyperparameters."""
    reset_optimizer: bool = True
    """Start each task with a fresh Adam state (the parameters are always carried over)."""


class PPOTLState(NamedTuple):
    """params: ActorCriticParams; opt_state: Adam state; rng: PRNG key; task_index: i32[], tasks learnt so far."""

    params: networks.ActorCriticParams
    opt_state: Any
    rng: jax.Array
    task_index: jax.Array


class ScratchState(NamedTuple):
    """The method ``ppo``'s state: PPO+TL's fields and ``fresh``, the initial parameters every task starts from."""

    params: networks.ActorCriticParams
    opt_state: Any
    rng: jax.Array
    task_index: jax.Array
    fresh: networks.ActorCriticParams


def make(family: Family, config: PPOTLConfig = PPOTLConfig(), progress_fn: Optional[ProgressFn] = None,
         scratch: bool = False) -> Method:
    """PPO+TL; with ``scratch``, the method ``ppo``: every task starts from the parameters ``init`` drew (kept in
    the state) and a fresh Adam state. Not a new draw per task: an orthogonal draw inside the vmapped program
    runs batched QR kernels, which can deadlock XLA:CPU's thread pool (``jcomps.runner.hostdevices``; it hung a PNC
    study), and tasks learnt from one initialisation are as independent of each other as from several."""
    optimizer = ppo.make_optimizer(config.ppo)

    def init(rng: jax.Array) -> PPOTLState:
        rng, k = jax.random.split(rng)
        params = ppo.init_params(config.ppo, family, k)
        if scratch:
            return ScratchState(params, optimizer.init(params), rng, jax.numpy.int32(0), params)
        return PPOTLState(params, optimizer.init(params), rng, jax.numpy.int32(0))

    def learn_task(state: PPOTLState, task) -> tuple[PPOTLState, TaskMetrics]:
        rng, k = jax.random.split(state.rng)
        params = state.fresh if scratch else state.params
        params = params._replace(policy=config.ppo.task_start(params.policy))
        opt_state = optimizer.init(params) if config.reset_optimizer or scratch else state.opt_state
        out = ppo.rl_step(config.ppo, family, params, opt_state, task, k,
                          progress_fn=with_fields(progress_fn, task=state.task_index))
        new_state = PPOTLState(out.params, out.opt_state, rng, state.task_index + 1)
        if scratch:
            new_state = ScratchState(*new_state, state.fresh)
        return new_state, TaskMetrics(out.iterations, out.solved, out.metrics, policy_health=out.health)

    return Method("ppo" if scratch else "ppo_tl", config, family, init, learn_task)


def make_scratch(family: Family, config: PPOTLConfig = PPOTLConfig(),
                 progress_fn: Optional[ProgressFn] = None) -> Method:
    """The method ``ppo``: single-task PPO from a random initialisation on every task (no transfer)."""
    return make(family, config, progress_fn, scratch=True)
