"""Point Goal: a 2-D point mass that must reach a goal on a circle (our cheap family, not in the paper).

It exists so that everything, the meta-learning effect included, can be shown on a CPU in minutes. The state
is the point's position; the observation is the same position (the goal is not observed: it must be learnt
from reward, as in Ant Goal). The goals of the sequences lie on a circle of radius ``GOAL_RADIUS`` at the
angles of the paper's Ant sequence.

Success threshold calibration (as the paper did for its families, from single-task PPO): see
``docs/families.md``; ``benchmarks/calibrate_point_goal.py`` reproduces it.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jcomps.envs import base, sequences

GOAL_RADIUS = 2.0
MAX_STEP = 0.1  # metres moved per step at full action
SUCCESS_RADIUS = 0.2
CTRL_COST = 0.01
RESET_NOISE = 0.1
MAX_STEPS = 100
SUCCESS_THRESHOLD = 0.7
BUDGET = 300


class PointGoalTask(NamedTuple):
    """goal: f32[..., 2], the goal position."""

    goal: jax.Array


def make_task(angles_deg: jax.Array) -> PointGoalTask:
    rad = jnp.deg2rad(jnp.asarray(angles_deg, jnp.float32))
    return PointGoalTask(goal=GOAL_RADIUS * jnp.stack([jnp.cos(rad), jnp.sin(rad)], axis=-1))


def reward_and_success(pos: jax.Array, action: jax.Array, task: PointGoalTask):
    """Reward −‖pos − goal‖ − 0.01·Σa² and success ‖pos − goal‖ < 0.2 for the position after a step."""
    dist = jnp.linalg.norm(pos - task.goal)
    reward = -dist - CTRL_COST * jnp.sum(jnp.square(action))
    return reward, (dist < SUCCESS_RADIUS).astype(jnp.float32)


def reset(rng: jax.Array, task: PointGoalTask) -> base.EnvState:
    del task
    pos = jax.random.uniform(rng, (2,), jnp.float32, -RESET_NOISE, RESET_NOISE)
    return base.make_env_state(pos, pos)


def step(state: base.EnvState, action: jax.Array, task: PointGoalTask) -> base.EnvState:
    pos = state.sim + MAX_STEP * action
    reward, success = reward_and_success(pos, action, task)
    return base.make_env_state(pos, pos, reward, 0.0, success, state.t)


def make() -> base.Family:
    return base.Family(
        name="point_goal",
        obs_size=2,
        action_size=2,
        max_steps=MAX_STEPS,
        success_threshold=SUCCESS_THRESHOLD,
        default_budget=BUDGET,
        task_values=tuple(float(a) for a in sequences.ANT_ANGLES_DEG),
        held_out_values=sequences.HELD_OUT_ANGLES_DEG,
        value_range=(-360.0, 360.0),
        value_name="goal angle in degrees", value_unit="°",
        make_task=make_task,
        reset_fn=reset,
        step_fn=step,
    )
