"""PPO+TL: PPO on each task, parameters carried to the next task, no meta step (the paper's baseline); and PPO
from scratch: a fresh random policy for every task (the single-task reference the paper tunes PPO on)."""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple, Optional

import jax

from jcomps import networks, ppo
from jcomps.envs.base import Family
from jcomps.progress import ProgressFn, with_fields
from jcomps.methods.base import Method, TaskMetrics


@dataclasses.dataclass(frozen=True)
class PPOTLConfig:
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


def make(family: Family, config: PPOTLConfig = PPOTLConfig(), progress_fn: Optional[ProgressFn] = None,
         scratch: bool = False) -> Method:
    """PPO+TL; with ``scratch``, the method ``ppo``: every task starts from freshly initialised parameters (and
    a fresh Adam state), drawn from the method's own random stream."""
    optimizer = ppo.make_optimizer(config.ppo)

    def init(rng: jax.Array) -> PPOTLState:
        rng, k = jax.random.split(rng)
        params = ppo.init_params(config.ppo, family, k)
        return PPOTLState(params, optimizer.init(params), rng, jax.numpy.int32(0))

    def learn_task(state: PPOTLState, task) -> tuple[PPOTLState, TaskMetrics]:
        rng, k = jax.random.split(state.rng)
        if scratch:
            k, k_init = jax.random.split(k)
            params = ppo.init_params(config.ppo, family, k_init)
        else:
            params = state.params
        opt_state = optimizer.init(params) if config.reset_optimizer or scratch else state.opt_state
        out = ppo.rl_step(config.ppo, family, params, opt_state, task, k,
                          progress_fn=with_fields(progress_fn, task=state.task_index))
        new_state = PPOTLState(out.params, out.opt_state, rng, state.task_index + 1)
        return new_state, TaskMetrics(out.iterations, out.solved, out.metrics)

    return Method("ppo" if scratch else "ppo_tl", config, family, init, learn_task)


def make_scratch(family: Family, config: PPOTLConfig = PPOTLConfig(),
                 progress_fn: Optional[ProgressFn] = None) -> Method:
    """The method ``ppo``: single-task PPO from a random initialisation on every task (no transfer)."""
    return make(family, config, progress_fn, scratch=True)
