"""The one interface every continual-learning method implements.

A method is data plus pure functions (as in optax):

- ``method.init(rng) -> State``: the method's whole state (parameters, optimiser states, rng, counters).
- ``method.learn_task(state, task) -> (State, TaskMetrics)``: learn one task of the sequence. Progress goes to the
  ``progress_fn`` the method was made with (``jcomps.progress``), tagged with ``state.task_index``.

Every state has a field ``params`` (``networks.ActorCriticParams``): the parameters the method would start its
next task from. Evaluations (backward transfer, held-out adaptation) read the policy there.

``config`` and ``family`` are bound when the method is made, so both functions are jittable with array
arguments only; the continual loop (``jcomps.continual``) never knows which method it runs.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, Optional

import jax

from jcomps.training import acting
from jcomps.training.meta import MetaMetrics
from jcomps.training.plasticity import PolicyHealth
from jcomps.training.rl_loop import IterationMetrics


class TaskMetrics(NamedTuple):
    """What ``learn_task`` reports about one task.

    Attributes:
      iterations: i32[], iterations-to-success (the budget if the threshold was never reached).
      solved: bool[], whether the success threshold was reached within the budget.
      per_iteration: IterationMetrics with fields of length ``budget``, masked by ``per_iteration.valid``.
      meta: the health of the meta phase that followed the task (``jcomps.training.meta.MetaMetrics``) for the methods
        with CoMPS's meta step; None for the others.
      policy_health: the exploration std, entropy and hidden-unit saturation of the policy the task's RL step
        started from and ended with (``jcomps.training.plasticity.PolicyHealth``) for the methods whose policy is a
        Gaussian with a state-independent std; None for the others (PEARL) and in runs made before it was measured.
    """

    iterations: jax.Array
    solved: jax.Array
    per_iteration: IterationMetrics
    meta: Optional[MetaMetrics] = None
    policy_health: Optional[PolicyHealth] = None


class Method(NamedTuple):
    """A continual-learning method bound to a family and a config.

    Attributes:
      name: registry name (e.g. ``ppo_tl``).
      config: the method's frozen config dataclass.
      family: the task family it learns on.
      init: ``rng -> State``.
      learn_task: ``(State, task) -> (State, TaskMetrics)``.
      env_steps_per_iteration: env steps one iteration collects; None: one batch of ``config.ppo.num_trajectories``
        episodes of T_max steps (``env_steps_per_iteration(method)`` resolves it).
      env_steps_per_task: env steps every task costs beyond its counted iterations (PNC's compress phase, which
        runs after the threshold is met); a solved task's samples-to-success include them, an unsolved task's
        count (the budget's iterations) already does.
      env_steps_before_task: env steps every task costs before its first iteration, solved or not (PEARL's
        collection with z from the prior, oyster's ``num_initial_steps``); samples-to-success include them.
      actor: how the method's policies act in rollouts (``jcomps.training.acting.Actor``): the Gaussian MLP policy's
        (``acting.GAUSSIAN``) for the PPO-based methods, whose evaluated policy ``state.params.policy`` is one; PEARL
        brings its tanh-Gaussian's.
      policy_for: ``(state, slot i32[], task, rng) -> policy``, the policy that acts on ``task``, the task learnt
        in ``slot`` (backward transfer, forgetting, replays); None: ``state.params.policy`` on every task. PEARL's
        infers its latent from the slot's replay buffer; MAML+TL's adapts θ by its inner step on fresh data of
        ``task``.
      adapt: ``(state, task, rng, iterations) -> (mean_return f32[iterations], success_rate f32[iterations])``,
        the method's own meta-test on a held-out task, nothing kept; None: PPO from ``state.params``
        (``continual.heldout_adaptation``).
    """

    name: str
    config: Any
    family: Any
    init: Callable[[jax.Array], Any]
    learn_task: Callable[[Any, Any], tuple[Any, TaskMetrics]]
    env_steps_per_iteration: Optional[int] = None
    env_steps_per_task: int = 0
    env_steps_before_task: int = 0
    actor: acting.Actor = acting.GAUSSIAN
    policy_for: Optional[Callable] = None
    adapt: Optional[Callable] = None


def collection(config) -> Any:
    """The part of a method config that holds ``num_trajectories`` (episodes per iteration) and ``budget`` (with
    ``budget_for(family)``), as the config's ``collection()`` says: its ``ppo`` part for the PPO-based methods (their
    configs derive from ``ppo.PPOBased``), the config itself for PEARL."""
    if not callable(getattr(type(config), "collection", None)):
        raise TypeError(f"{type(config).__name__} has no collection(): a method config says where its episodes per "
                        "iteration and budget are (derive from jcomps.training.ppo.PPOBased for a PPO part named ppo)")
    return config.collection()


def task_slots(config) -> Optional[int]:
    """The task slots a method config's state holds (its field ``max_tasks``: CoMPS's experience stores, PEARL's
    replay buffers), None for a method that learns any number of tasks. The one place that asks a config for it."""
    return getattr(config, "max_tasks", None)


def env_steps_per_iteration(method: Method) -> int:
    """Env steps one iteration of ``method`` collects (MAML+TL collects two batches per iteration)."""
    if method.env_steps_per_iteration is not None:
        return method.env_steps_per_iteration
    return collection(method.config).num_trajectories * method.family.max_steps


def policy_for(method: Method, state, slot, task, rng):
    """The policy of ``state`` that acts on ``task``, the task learnt in ``slot`` (``Method.policy_for``)."""
    if method.policy_for is None:
        return state.params.policy
    return method.policy_for(state, slot, task, rng)
