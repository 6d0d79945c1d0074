"""The paper's MuJoCo families on MJX through brax: Half-Cheetah Velocity, Ant Goal, Ant Direction.

Physics comes from brax's ``ant`` and ``halfcheetah`` models on the ``mjx`` backend (5 physics frames per
env step, dt = 0.05 s). Both use fast MJX solver settings (Newton, 1 iteration, 4 line-search iterations,
Euler damping off): brax gives them to the Ant; we give the same to the Half-Cheetah, whose XML defaults make it
8x slower. Rewards, terminations and success criteria follow the paper's appendix A (PEARL's environments with
the control cost scaled by 0.1 for the Ants):

- ``cheetah_vel``: reward −|v − v_g| − 0.05·Σa²; success |v − v_g| < max(0.3·|v_g|, 0.1) (the floor is our
  choice: with the paper's 0.3·|v_g| the v_g = 0 task could never succeed); threshold 0.45; T_max 200.
- ``ant_goal``: reward −‖xy − g‖₁ − 0.1·(0.1·Σa²); success ‖xy − g‖₁ < 0.5; threshold 0.3; goals at radius 3;
  never terminates; T_max 200. The observation adds the torso's x, y to brax's 27 (the goal must be found
  from position).
- ``ant_dir``: reward v·d − 0.1·(0.5·Σa²) + 1; terminates when torso z ∉ [0.2, 1]; success ‖v̂ − d‖ < 0.4 and
  ‖v‖ > 0.5 m/s; threshold 0.5; T_max 200.

Velocities are finite differences of the torso position over one env step, as in PEARL. The contact cost of the
PEARL Ants is zero here: MJX does not compute the external contact forces it needs (brax omits it too), which is
also what PEARL's environments computed under MuJoCo >= 2.0, where ``cfrc_ext`` is all zeros.
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco

from jcomps.envs import base, sequences

MAX_STEPS = 200
ANT_GOAL_RADIUS = 3.0
FAST_MJX_OPTIONS = {
    "opt.solver": mujoco.mjtSolver.mjSOL_NEWTON,
    "opt.disableflags": mujoco.mjtDisableBit.mjDSBL_EULERDAMP,
    "opt.iterations": 1,
    "opt.ls_iterations": 4,
}


class CheetahVelTask(NamedTuple):
    """velocity: f32[...], the goal forward velocity in m/s."""

    velocity: jax.Array


class AntGoalTask(NamedTuple):
    """goal: f32[..., 2], the goal position in the plane."""

    goal: jax.Array


class AntDirTask(NamedTuple):
    """direction: f32[..., 2], the unit goal direction in the plane."""

    direction: jax.Array


def _unit(angles_deg):
    rad = jnp.deg2rad(jnp.asarray(angles_deg, jnp.float32))
    return jnp.stack([jnp.cos(rad), jnp.sin(rad)], axis=-1)


# ---------------------------------------------------------------- rewards and success (pure, testable)

def cheetah_reward_and_success(velocity, action, task: CheetahVelTask):
    """Reward and success of a Half-Cheetah step with forward ``velocity`` (m/s) and ``action``."""
    err = jnp.abs(velocity - task.velocity)
    reward = -err - 0.05 * jnp.sum(jnp.square(action))
    tol = jnp.maximum(0.3 * jnp.abs(task.velocity), 0.1)
    return reward, (err < tol).astype(jnp.float32)


def ant_goal_reward_and_success(xy, action, task: AntGoalTask):
    """Reward and success of an Ant Goal step ending with the torso at ``xy``."""
    dist = jnp.sum(jnp.abs(xy - task.goal))
    reward = -dist - 0.1 * (0.1 * jnp.sum(jnp.square(action)))
    return reward, (dist < 0.5).astype(jnp.float32)


def ant_dir_reward_and_success(velocity_xy, torso_z, action, task: AntDirTask):
    """Reward, success and termination of an Ant Direction step with planar torso velocity ``velocity_xy``."""
    reward = jnp.dot(velocity_xy, task.direction) - 0.1 * (0.5 * jnp.sum(jnp.square(action))) + 1.0
    speed = jnp.linalg.norm(velocity_xy)
    v_hat = velocity_xy / jnp.maximum(speed, 1e-8)
    success = (jnp.linalg.norm(v_hat - task.direction) < 0.4) & (speed > 0.5)
    done = (torso_z < 0.2) | (torso_z > 1.0)
    return reward, success.astype(jnp.float32), done.astype(jnp.float32)


# ---------------------------------------------------------------- physics

def _brax_env(model: str):
    from brax import envs as brax_envs

    with warnings.catch_warnings():  # brax's notice that its own pipelines are unmaintained; we use MJX
        warnings.simplefilter("ignore", UserWarning)
        env = brax_envs.get_environment(model, backend="mjx")
    env.sys = env.sys.tree_replace(FAST_MJX_OPTIONS)
    return env


def _reset_sim(env, rng):
    """brax's reset distribution: q0 + U(−0.1, 0.1) positions, 0.1·N(0, 1) velocities."""
    rng1, rng2 = jax.random.split(rng)
    q = env.sys.init_q + jax.random.uniform(rng1, (env.sys.q_size(),), minval=-0.1, maxval=0.1)
    qd = 0.1 * jax.random.normal(rng2, (env.sys.qd_size(),))
    return env.pipeline_init(q.astype(jnp.float32), qd.astype(jnp.float32))


def _cheetah_obs(ps):
    return jnp.concatenate([ps.q[1:], ps.qd])


def _ant_obs(ps):
    return jnp.concatenate([ps.q[2:], ps.qd])


def _ant_goal_obs(ps):
    return jnp.concatenate([ps.q[:2], ps.q[2:], ps.qd])


def _mjx_family(model: str, obs_fn, outcome_fn, **facts) -> base.Family:
    """A family on brax's ``model``: ``outcome_fn(q_before, q_after, action, task, dt) -> (reward, success, done)``."""
    env = _brax_env(model)
    dt = env.dt

    def reset(rng, task):
        del task
        ps = _reset_sim(env, rng)
        return base.make_env_state(ps, obs_fn(ps))

    def step(state, action, task):
        ps = env.pipeline_step(state.sim, action)
        reward, success, done = outcome_fn(state.sim.q, ps.q, action, task, dt)
        return base.make_env_state(ps, obs_fn(ps), reward, done, success, state.t)

    return base.Family(max_steps=MAX_STEPS, reset_fn=reset, step_fn=step, system=env.sys, **facts)


def _cheetah_outcome(q0, q, action, task, dt):
    reward, success = cheetah_reward_and_success((q[0] - q0[0]) / dt, action, task)
    return reward, success, 0.0


def _ant_goal_outcome(q0, q, action, task, dt):
    del q0, dt
    reward, success = ant_goal_reward_and_success(q[:2], action, task)
    return reward, success, 0.0


def _ant_dir_outcome(q0, q, action, task, dt):
    return ant_dir_reward_and_success((q[:2] - q0[:2]) / dt, q[2], action, task)


def _make_cheetah() -> base.Family:
    return _mjx_family(
        "halfcheetah", _cheetah_obs, _cheetah_outcome,
        name="cheetah_vel", obs_size=17, action_size=6, success_threshold=0.45,
        default_budget=500, task_values=tuple(sequences.CHEETAH_VELOCITIES),
        held_out_values=sequences.HELD_OUT_VELOCITIES, value_range=(-3.0, 3.0),
        value_name="goal velocity in m/s", value_unit="m/s",
        make_task=lambda v: CheetahVelTask(jnp.asarray(v, jnp.float32)),
    )


def _make_ant(name: str) -> base.Family:
    goal = name == "ant_goal"
    return _mjx_family(
        "ant", _ant_goal_obs if goal else _ant_obs, _ant_goal_outcome if goal else _ant_dir_outcome,
        name=name, obs_size=29 if goal else 27, action_size=8,
        success_threshold=0.3 if goal else 0.5, default_budget=1000,
        task_values=tuple(float(a) for a in sequences.ANT_ANGLES_DEG),
        held_out_values=sequences.HELD_OUT_ANGLES_DEG, value_range=(-360.0, 360.0),
        value_name="goal angle in degrees" if goal else "direction angle in degrees", value_unit="°",
        make_task=(lambda a: AntGoalTask(ANT_GOAL_RADIUS * _unit(a))) if goal else (lambda a: AntDirTask(_unit(a))),
        can_terminate=not goal,
    )


def make(name: str) -> base.Family:
    if name == "cheetah_vel":
        return _make_cheetah()
    if name in ("ant_goal", "ant_dir"):
        return _make_ant(name)
    raise ValueError(f"unknown MuJoCo family {name!r}; allowed: cheetah_vel, ant_goal, ant_dir")
