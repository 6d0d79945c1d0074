"""MetaWorld: the paper's manipulation family, through the real ``metaworld`` package (v3 tasks).

A task is an environment, Push-Wall (P), Button-Press-Wall (B) or Hammer (H), and a goal index k, variant k of
the environment's 50 (``metaworld_host.variants``). Its task parameter value is the code ``100·e + k``
(e = 0, 1, 2 for P, B, H). The paper's non-stationary sequence is P-0, B-1, H-2, P-3, … (goal index = position,
39 tasks); the held-out tasks continue the pattern past it (P-39 … H-47), so their goal indices are never in
the sequence.

MJX cannot load these scenes, so the simulator is MuJoCo's C library on the host, reached from the jitted
programs by ``jax.pure_callback``. The family is still pure: ``EnvState.sim`` holds the whole simulator state
(float64 bits as uint32 pairs, see ``metaworld_host``), so the methods, their chunk programs, checkpoints and
exact resume work unchanged. Under ``vmap`` (environments, seeds) each step is one callback for the whole
batch, which ``metaworld_host.Pool`` spreads over worker processes (every core by default;
``JCOMPS_METAWORLD_WORKERS`` sets the number). Resets are deterministic (MetaWorld's resets of a frozen variant
are); the policy's noise is the only randomness, so runs are reproducible whatever the number of workers.

The paper's rules: T_max = 150 (a truncation: MetaWorld never terminates); the success rate is the fraction of
trajectories with at least one success step; threshold 0.2; budget 500. The goal is hidden from the
observation (ML1's tasks): as in the other families, the task must be inferred from reward.
"""

from __future__ import annotations

import dataclasses
import functools
import re
import threading
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jcomps.envs import base, host_acting
from jcomps.envs import metaworld_host as host

SUCCESS_THRESHOLD = 0.2
BUDGET = 500
NUM_SEQUENCE = 39
NUM_HELD_OUT = 9


def code(env: int, goal_index: int) -> int:
    """The task parameter value of goal variant ``goal_index`` of environment ``env`` (0: P, 1: B, 2: H)."""
    return 100 * env + goal_index


def label(value) -> str:
    """The paper's name of a task, e.g. ``P-0``, ``B-1``, ``H-2``."""
    value = int(round(float(value)))
    return f"{host.LETTERS[value // 100]}-{value % 100}"


SEQUENCE = tuple(float(code(i % 3, i)) for i in range(NUM_SEQUENCE))
"""The paper's non-stationary sequence, P-0, B-1, H-2, …, H-38, as task codes."""
HELD_OUT = tuple(float(code(i % 3, i)) for i in range(NUM_SEQUENCE, NUM_SEQUENCE + NUM_HELD_OUT))
"""P-39, B-40, H-41, …, H-47: goal indices the sequence never uses."""


class MetaWorldTask(NamedTuple):
    """env: i32[...], 0 (Push-Wall), 1 (Button-Press-Wall) or 2 (Hammer); variant: i32[...], the goal index."""

    env: jax.Array
    variant: jax.Array


def make_task(values: jax.Array, reward: str = "v2") -> MetaWorldTask:
    """The task of each code; ``reward`` picks MetaWorld's reward function (``metaworld_host.REWARD_VERSIONS``),
    carried in the host environment index (``env`` 0-2 for "v2", 3-5 for "v1")."""
    v = jnp.round(jnp.asarray(values, jnp.float32)).astype(jnp.int32)
    offset = len(host.ENV_NAMES) * host.REWARD_VERSIONS.index(reward)
    return MetaWorldTask(env=v // 100 + offset, variant=v % 100)


_STATE_WORDS = 2 * host.STATE_SIZE  # float64 bits as uint32 pairs


_POOL_LOCK = threading.Lock()


@functools.cache
def _pool() -> host.Pool:
    return host.Pool()


def pool() -> host.Pool:
    """The process-wide stepping pool (workers start on the first batch that needs them); ``pool.cache_clear()``
    forgets it (close it first), so that the next call reads ``JCOMPS_METAWORLD_WORKERS`` again."""
    with _POOL_LOCK:  # one pool even when two devices' callbacks ask at once
        return _pool()


pool.cache_clear = _pool.cache_clear


def _host_reset(env, variant):
    # In a worker, like every MuJoCo call: on XLA's callback thread, MuJoCo's bindings re-take the GIL with the
    # thread state Python registered for that OS thread, not the one JAX's callback holds it with, and loading a
    # model there deadlocked (twice in the benchmark's full run; the thread waited on the GIL it held itself).
    shape = np.shape(env)
    states, obs = pool().reset(np.array(env, np.int64).reshape(-1), np.array(variant, np.int64).reshape(-1))
    return (np.ascontiguousarray(states).view(np.uint32).reshape(*shape, _STATE_WORDS),
            obs.astype(np.float32).reshape(*shape, host.OBS_SIZE))


def _host_step(env, variant, sim, action):
    shape = np.shape(env)
    env, variant = np.array(env, np.int64).reshape(-1), np.array(variant, np.int64).reshape(-1)
    states = np.array(sim, np.uint32).reshape(-1, _STATE_WORDS).view(np.float64)
    action = np.array(action, np.float32).reshape(-1, host.ACTION_SIZE)
    states, obs, reward, success = pool().step(env, variant, states, action)
    return (np.ascontiguousarray(states).view(np.uint32).reshape(*shape, _STATE_WORDS),
            obs.astype(np.float32).reshape(*shape, host.OBS_SIZE),
            reward.astype(np.float32).reshape(shape), success.astype(np.float32).reshape(shape))


def reset(rng: jax.Array, task: MetaWorldTask) -> base.EnvState:
    del rng  # a frozen MetaWorld variant always starts from the same state
    shapes = (jax.ShapeDtypeStruct((_STATE_WORDS,), jnp.uint32), jax.ShapeDtypeStruct((host.OBS_SIZE,), jnp.float32))
    sim, obs = jax.pure_callback(_host_reset, shapes, task.env, task.variant, vmap_method="broadcast_all")
    return base.make_env_state(sim, obs)


def step(state: base.EnvState, action: jax.Array, task: MetaWorldTask) -> base.EnvState:
    shapes = (jax.ShapeDtypeStruct((_STATE_WORDS,), jnp.uint32), jax.ShapeDtypeStruct((host.OBS_SIZE,), jnp.float32),
              jax.ShapeDtypeStruct((), jnp.float32), jax.ShapeDtypeStruct((), jnp.float32))
    sim, obs, reward, success = jax.pure_callback(_host_step, shapes, task.env, task.variant, state.sim, action,
                                                  vmap_method="broadcast_all")
    return base.make_env_state(sim, obs, reward, 0.0, success, state.t)


def _host_rollout(kind, policy, env, variant, noise, active):
    """The callback of ``host_rollout``: arguments with the leading axes of any vmaps (``broadcast_all``). Groups
    (one policy and task each) whose ``active`` is False are not stepped: their outputs are zeros."""
    noise = np.asarray(noise, np.float32)
    lead, (steps, batch, actions) = noise.shape[:-3], noise.shape[-3:]
    groups = int(np.prod(lead, dtype=np.int64))
    run = np.flatnonzero(np.broadcast_to(np.asarray(active, bool), lead).reshape(groups))
    flat = host_acting.plain(jax.tree.map(lambda x: np.asarray(x).reshape((groups, *np.shape(x)[len(lead):])),
                                          policy))
    policies = [jax.tree.map(lambda x, g=g: x[g], flat) for g in run]
    env, variant = (np.asarray(x, np.int64).reshape(groups)[run] for x in (env, variant))
    noise = noise.reshape(groups, steps, batch, actions)[run]
    # Episodes group-major: episode g·B + b is episode b of the g-th group run (one policy and task per group).
    outs = (np.zeros((groups, batch, steps + 1, host.OBS_SIZE), np.float32),
            np.zeros((groups, batch, steps, actions), np.float32), *(np.zeros((groups, batch, steps), np.float32)
                                                                       for _ in range(3)))
    if len(run):
        got = pool().rollout(kind, policies, np.repeat(np.arange(len(run)), batch), np.tile(np.arange(batch), len(run)),
                             np.repeat(env, batch), np.repeat(variant, batch),
                             noise.swapaxes(1, 2).reshape(len(run) * batch, steps, actions))
        for out, x in zip(outs, got):
            out[run] = x.reshape(len(run), batch, *x.shape[1:])

    def time_major(x):  # [G, B, T, ...] -> [*lead, T, B, ...]
        return np.ascontiguousarray(x.swapaxes(1, 2)).reshape(*lead, x.shape[2], batch, *x.shape[3:])

    obs, action, log_prob, reward, success = outs
    obs = time_major(obs)
    return (obs[..., :steps, :, :], time_major(action), time_major(log_prob), time_major(reward),
            time_major(success), np.ascontiguousarray(obs[..., steps, :, :]))


def host_rollout(kind: str, policy, task: MetaWorldTask, noise: jax.Array, active=True):
    """``Family.host_rollout``: whole episodes on the host (``metaworld_host.rollout`` over the pool), the policy
    evaluated by its NumPy twin ``kind``; one callback per rollout (per step: ``step``). Not run where ``active``
    (bool) is False: zeros."""
    steps, batch, actions = noise.shape
    f32 = functools.partial(jax.ShapeDtypeStruct, dtype=jnp.float32)
    shapes = (f32((steps, batch, host.OBS_SIZE)), f32((steps, batch, actions)), f32((steps, batch)),
              f32((steps, batch)), f32((steps, batch)), f32((batch, host.OBS_SIZE)))
    return jax.pure_callback(functools.partial(_host_rollout, kind), shapes, policy, task.env, task.variant,
                             noise, jnp.asarray(active, bool), vmap_method="broadcast_all")


@dataclasses.dataclass(frozen=True, eq=False)
class MetaWorldFamily(base.Family):
    """The MetaWorld family: task codes are checked to name a real task; success counts trajectories."""

    def success_rate(self, success: jax.Array, valid=None) -> jax.Array:
        """The fraction of the batch's trajectories with at least one success step (``success`` f32[T, B])."""
        return jnp.mean(jnp.max(success, axis=0))

    def parse_value(self, text: str) -> float:
        """``P-3``, ``B-1``, ``H-2`` (the paper's names) or a task code (``203``)."""
        m = re.fullmatch(r"\s*([PBH])-(\d+)\s*", str(text))
        if m is None:
            try:
                return super().parse_value(text)
            except ValueError as err:
                raise ValueError(f"{err}, or its name P-k, B-k or H-k (e.g. P-3)") from None
        if int(m.group(2)) >= host.NUM_VARIANTS:
            raise ValueError(f"{self.name}: task {text!r} does not exist; goal indices are 0-{host.NUM_VARIANTS - 1}")
        return float(code(host.LETTERS.index(m.group(1)), int(m.group(2))))

    def task_name(self, value: float) -> str:
        """The paper's name of a task code, e.g. ``B-2`` for 102."""
        return label(value)

    def tasks(self, values):
        arr = base.validate_values(self, values)
        for v in arr:
            if v != np.round(v) or not (v % 100 < host.NUM_VARIANTS):
                raise ValueError(f"{self.name}: task value {float(v)} is not a task; {self.value_name}")
        return self.make_task(jnp.asarray(arr, jnp.float32))


def make(reward: str = "v2") -> base.Family:
    """The family with MetaWorld's reward function ``reward``: "v2" (``metaworld``, the v3 environments' default,
    the reward of the v2 environments the paper used) or "v1" (``metaworld_v1``, MetaWorld v1's original reward;
    the same tasks, observations and rules; success is MetaWorld's rule for each version, which differ only on
    Push-Wall: v1 measures the puck's distance to the goal in the plane, v2 in 3-D, and the two sit at one height)."""
    if reward not in host.REWARD_VERSIONS:
        raise ValueError(f"metaworld reward: {reward!r} is not one of {', '.join(host.REWARD_VERSIONS)}")
    return MetaWorldFamily(
        name="metaworld" if reward == "v2" else f"metaworld_{reward}", obs_size=host.OBS_SIZE,
        action_size=host.ACTION_SIZE, max_steps=host.MAX_STEPS,
        success_threshold=SUCCESS_THRESHOLD, default_budget=BUDGET, task_values=SEQUENCE,
        held_out_values=HELD_OUT, value_range=(0.0, 100.0 * (len(host.ENV_NAMES) - 1) + host.NUM_VARIANTS - 1),
        value_name=(f"a task code 100·e + k: environment e (0 Push-Wall, 1 Button-Press-Wall, 2 Hammer) and goal "
                    f"index k (an integer 0-{host.NUM_VARIANTS - 1})"),
        make_task=functools.partial(make_task, reward=reward), reset_fn=reset, step_fn=step,
        host_rollout=host_rollout,
    )
