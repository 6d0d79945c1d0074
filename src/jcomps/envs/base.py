"""The task-family interface shared by every environment in jcomps.

A *family* is a set of MDPs with the same state and action spaces that differ only in a task parameter (a goal,
a direction, a velocity). Everything here is a pure function of explicit inputs, so it can be jitted, vmapped
over environments and seeds, and scanned over time and over tasks:

- ``family.reset(rng, task) -> EnvState``
- ``family.step(state, action, task) -> EnvState``

An episode lasts exactly ``family.max_steps`` steps (T_max). Reaching T_max is a *truncation*: the learner must
bootstrap the value of the last observation. A family may also *terminate* an episode early (Ant Direction when
the torso leaves its healthy height range); from then on the state is absorbing: it no longer changes, and
reward and success are zero. ``EnvState.done`` marks termination only, never truncation.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from jcomps.numerics import masked_mean


class EnvState(NamedTuple):
    """State of one environment (add leading axes with ``vmap``).

    Attributes:
      sim: family-specific simulator state (a pytree).
      obs: f32[obs_size], the observation of the current state.
      reward: f32[], reward of the transition that led here (0 after reset).
      done: f32[], 1.0 once the episode has terminated (absorbing), else 0.0. Truncation at T_max is not
        termination and never sets it.
      success: f32[], the family's per-step success indicator for the transition that led here.
      t: i32[], number of steps taken since reset.
    """

    sim: Any
    obs: jax.Array
    reward: jax.Array
    done: jax.Array
    success: jax.Array
    t: jax.Array


def strong(tree):
    """Casts every leaf to a strongly typed array of its own dtype.

    Weak-typed leaves (Python scalars, ``jnp.full(n, 0.5)``) make a jitted function fed with its own output
    retrace; we give every state leaf an explicit dtype instead.
    """
    return jax.tree.map(lambda x: jnp.asarray(x, dtype=jnp.asarray(x).dtype), tree)


def make_env_state(sim, obs, reward=0.0, done=0.0, success=0.0, t=0) -> EnvState:
    """Builds an ``EnvState`` with the dtypes every family uses (float32 scalars, int32 step counter)."""
    return EnvState(
        sim=strong(sim),
        obs=jnp.asarray(obs, jnp.float32),
        reward=jnp.asarray(reward, jnp.float32),
        done=jnp.asarray(done, jnp.float32),
        success=jnp.asarray(success, jnp.float32),
        t=jnp.asarray(t, jnp.int32),
    )


@dataclasses.dataclass(frozen=True, eq=False)
class Family:
    """A task family: the pure env functions plus the facts the paper attaches to it.

    Instances are hashable by identity, so a family can be a static argument of ``jax.jit``.

    Attributes:
      name: the family's name, as used everywhere (CLI included).
      obs_size: length of the observation vector.
      action_size: length of the action vector; actions are clipped to [-1, 1] by ``step``.
      max_steps: T_max, the episode length (a truncation, not a termination).
      success_threshold: success rate at which the RL step stops on a task.
      default_budget: iterations per task the paper gives this family (N).
      task_values: the paper's non-stationary sequence, as task parameter values (degrees or m/s).
      held_out_values: task parameter values never trained on, for meta-test adaptation.
      value_range: inclusive (low, high) bounds a task parameter value must lie in.
      value_name: what a task parameter value means (for messages and docs).
      value_unit: the unit of a task parameter value, for plots ("m/s", "°"; "" for a code).
      make_task: maps a float32 array of task parameter values (any shape) to the family's task pytree
        with the same leading shape.
      can_terminate: whether ``step_fn`` can ever set ``done`` (only then does ``step`` pay for freezing
        terminated states).
      reset_fn, step_fn: the family's raw physics; use ``reset`` and ``step``, which add dtypes and the
        absorbing-termination rule.
      system: the brax ``System`` the MuJoCo families simulate (``EnvState.sim`` is its pipeline state), for
        rendering with ``brax.io.html``; None for Point Goal.
      host_rollout: for a family simulated on the host (MetaWorld), whole rollouts run there:
        ``host_rollout(kind, policy, task, noise f32[T, B, A], active bool[]) -> (obs f32[T, B, O], action
        f32[T, B, A], log_prob f32[T, B], reward f32[T, B], success f32[T, B], last_obs f32[B, O])`` with the
        policy evaluated by its NumPy twin ``kind`` (``jcomps.envs.host_acting``); where ``active`` is False the result
        is discarded (``acting.only_if``), so the host may skip it and return zeros. ``acting.rollout`` uses it
        when the ``act`` has a twin, and steps through ``step`` otherwise. None: rollouts always step through
        ``step``.
    """

    name: str
    obs_size: int
    action_size: int
    max_steps: int
    success_threshold: float
    default_budget: int
    task_values: tuple[float, ...]
    held_out_values: tuple[float, ...]
    value_range: tuple[float, float]
    value_name: str
    make_task: Callable[[jax.Array], Any]
    reset_fn: Callable[[jax.Array, Any], EnvState]
    step_fn: Callable[[EnvState, jax.Array, Any], EnvState]
    can_terminate: bool = False
    value_unit: str = ""
    system: Any = None
    host_rollout: Any = None

    def reset(self, rng: jax.Array, task) -> EnvState:
        """Starts an episode of ``task``; ``rng`` is a PRNG key. Returns the initial ``EnvState``."""
        return self.reset_fn(rng, task)

    def step(self, state: EnvState, action: jax.Array, task) -> EnvState:
        """Advances one step with ``action`` f32[action_size] (clipped to [-1, 1]).

        After termination the state is absorbing: unchanged, with zero reward and success.
        """
        action = jnp.clip(jnp.asarray(action, jnp.float32), -1.0, 1.0)
        nxt = self.step_fn(state, action, task)
        nxt = make_env_state(nxt.sim, nxt.obs, nxt.reward, nxt.done, nxt.success, state.t + 1)
        if not self.can_terminate:
            return nxt
        frozen = state._replace(
            reward=jnp.zeros_like(state.reward), success=jnp.zeros_like(state.success), t=state.t + 1
        )
        terminated = state.done > 0
        return jax.tree.map(lambda a, b: jnp.where(terminated, a, b), frozen, nxt)

    def success_rate(self, success: jax.Array, valid: Optional[jax.Array] = None) -> jax.Array:
        """Success rate of an iteration: the mean per-step indicator over the steps of the batch that were taken.

        ``success`` is f32[T, B] (time-major); ``valid`` f32[T, B] marks the steps taken by a live episode
        (``Trajectory.valid``). The paper averages "across all samples": a family that can terminate (Ant
        Direction) averages over the steps taken, so an episode that fell contributes its steps and no more;
        the absorbing steps after a fall are not samples. Without ``valid`` (or for a family that never
        terminates, where every step is taken) it is the mean over all T_max·B steps.
        """
        if valid is None or not self.can_terminate:
            return jnp.mean(success)
        return masked_mean(success, valid)

    def tasks(self, values) -> Any:
        """Validated task pytree for task parameter ``values`` (a 1-D sequence), stacked on axis 0."""
        return self.make_task(jnp.asarray(validate_values(self, values), jnp.float32))

    def parse_value(self, text: str) -> float:
        """A task parameter value from its name on a command line (a number: degrees, m/s, a code); families
        with names of their own (MetaWorld's ``P-3``) take those too. Not yet range-checked: see ``parse_values``."""
        try:
            return float(text)
        except (TypeError, ValueError):
            raise ValueError(f"{self.name}: task {text!r} is not a number; a task is {self.value_name}") from None

    def task_name(self, value: float) -> str:
        """The canonical name of a task parameter value (what ``parse_value`` reads back to it): the shortest of
        ``%g`` and ``repr`` that is exact, e.g. ``10`` for "10.0", ``-45.5``."""
        value = float(value)
        short = f"{value:g}"
        return short if float(short) == value else repr(value)

    def parse_values(self, texts) -> np.ndarray:
        """``parse_value`` of each name, checked to be tasks of the family (``tasks``): f32[len(texts)]."""
        values = np.asarray([self.parse_value(t) for t in texts], np.float32)
        self.tasks(values)
        return values


def validate_values(family: Family, values) -> np.ndarray:
    """Checks a list of task parameter values and returns it as a float32 array, or raises ValueError."""
    what = f"a non-empty 1-D list of numbers ({family.value_name})"
    arr = np.asarray(values, dtype=object) if not isinstance(values, np.ndarray) else values
    if arr.ndim != 1 or arr.size == 0:
        raise ValueError(f"{family.name}: task values must be {what}, got shape {np.shape(arr)}")
    for v in arr:
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise ValueError(f"{family.name}: task values must be {what}, got {v!r}")
    arr = arr.astype(np.float64)
    low, high = family.value_range
    bad = ~np.isfinite(arr) | (arr < low) | (arr > high)
    if bad.any():
        raise ValueError(
            f"{family.name}: task value {float(arr[bad][0])} is out of range; {family.value_name} must be a "
            f"finite number in [{low}, {high}]"
        )
    return arr.astype(np.float32)
