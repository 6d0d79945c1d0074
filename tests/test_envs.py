"""Tests of the task families (``jcomps.envs``): determinism, jit/vmap agreement, dtypes, reward and success
formulas, absorbing termination, action clipping, the paper's task sequences and input validation.

MJX compilation is the expensive part on a CPU (tens of seconds per jitted function and family), so every
family compiles exactly three functions, once, shared by all tests through a module-level cache: an unbatched
``reset``, an unbatched ``T``-step ``rollout`` from a given state, and a vmapped reset+rollout over ``B``
environments. All three are guarded by ``chex.assert_max_traces(n=1)``, so any test that would make them
retrace (a shape, dtype or weak-type change in a state fed back in) fails instead of silently recompiling.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import re
from typing import Any, Callable

import chex
import hypothesis.extra.numpy as hnp
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from jcomps import envs
from jcomps.envs import mujoco as mj
from jcomps.envs import point_goal as pg

# The paper's sequences (appendix A), written out here on purpose rather than imported from the package.
ANT_ANGLES_DEG = [
    -171, 9, -162, 18, -153, 27, -144, 36, -135, 45, -126, 54, -117, 63, -108, 72, -99, 81, -90, 90,
    -81, 99, -72, 108, -63, 117, -54, 126, -45, 135, -36, 144, -27, 153, -18, 162, -9, 171, 0, 180,
]
CHEETAH_VELOCITIES = [
    -2.66, 0.14, -2.52, 0.28, -2.38, 0.42, -2.24, 0.56, -2.1, 0.7, -1.96, 0.84, -1.82, 0.98, -1.68, 1.12,
    -1.54, 1.26, -1.4, 1.4, -1.26, 1.54, -1.12, 1.68, -0.98, 1.82, -0.84, 1.96, -0.7, 2.1, -0.56, 2.24,
    -0.42, 2.38, -0.28, 2.52, -0.14, 2.66, 0.0, 2.8,
]
PAPER_VALUES = {
    "point_goal": ANT_ANGLES_DEG,
    "cheetah_vel": CHEETAH_VELOCITIES,
    "ant_goal": ANT_ANGLES_DEG,
    "ant_dir": ANT_ANGLES_DEG,
}
FAMILIES = ["point_goal", "cheetah_vel", "ant_goal", "ant_dir"]  # the JAX-simulated ones; metaworld: test_metaworld
MJX_DT = 0.05  # seconds per env step (5 physics frames), as documented in envs/mujoco.py

T = 5  # steps per test rollout
B = 3  # environments in the vmapped batch
EXACT_TOL = dict(rtol=1e-5, atol=1e-5)
# Batched and unbatched MJX steps differ by float reassociation, and contacts amplify it: from identical
# states, joint velocities (|qd| up to ~15) measured up to 0.036 apart after 5 Half-Cheetah steps, rewards 0.011.
# Solver internals (efc_*, qacc, ...) can differ by O(1) when a contact switches, so only the observable part
# of a rollout is compared after the reset.
MJX_TOL = dict(rtol=1e-2, atol=5e-2)


# ------------------------------------------------------------------------------------ compiled rollouts


def _at(tree, i):
    """Entry ``i`` of every leaf, as JAX arrays (dtype and weak type kept: use it for states fed back in)."""
    return jax.tree.map(lambda x: x[i], tree)


def _np_at(tree, i):
    """Entry ``i`` of every leaf, as NumPy arrays (no per-shape XLA compilation: use it for comparisons)."""
    return jax.tree.map(lambda x: np.asarray(x)[i], tree)


def _guarded_jit(fn: Callable, tag: str) -> Callable:
    """``jax.jit`` of ``fn`` that raises if ``fn`` is ever traced a second time.

    chex keys its trace counter on the definition site and the function's name; every family defines its
    functions at the same site, so the family name goes into the name to keep the counters apart.
    """
    fn.__name__ = f"{fn.__name__}_{tag}"
    fn.__qualname__ = fn.__name__
    return jax.jit(chex.assert_max_traces(fn, n=1))


@dataclasses.dataclass
class Rollouts:
    """A family's three compiled functions, their canonical inputs, and their outputs on those inputs."""

    fam: envs.Family
    reset: Callable  # (rng, task) -> EnvState
    rollout: Callable  # (state, task, f32[T, A]) -> EnvState stacked on T (the states after each step)
    batched: Callable  # (rng[B], task[B], f32[B, T, A]) -> (EnvState[B], EnvState[B, T])
    rngs: jax.Array
    tasks: Any
    actions: jax.Array
    s0: envs.EnvState  # reset(rngs[0], task(0))
    traj: envs.EnvState  # rollout(s0, task(0), actions[0])
    batch: tuple  # batched(rngs, tasks, actions)

    def task(self, i: int):
        return _at(self.tasks, i)


def _build(name: str) -> Rollouts:
    fam = envs.make(name)

    def reset(rng, task):
        return fam.reset(rng, task)

    def rollout(state, task, actions):
        def body(s, a):
            s = fam.step(s, a, task)
            return s, s

        return jax.lax.scan(body, state, actions)[1]

    def reset_and_rollout(rng, task, actions):
        s0 = fam.reset(rng, task)
        return s0, rollout(s0, task, actions)

    reset_jit = _guarded_jit(reset, name)
    rollout_jit = _guarded_jit(rollout, name)
    # chex.assert_max_traces must not wrap a transformed function, so the vmap goes inside.
    def batched(rngs, tasks, actions):
        return jax.vmap(reset_and_rollout)(rngs, tasks, actions)

    batched_jit = _guarded_jit(batched, name)

    rngs = jax.random.split(jax.random.key(0), B)
    tasks = envs.sequence(fam, "non-stationary", num_tasks=B)  # three different tasks
    actions = jax.random.uniform(jax.random.key(1), (B, T, fam.action_size), jnp.float32, -1.0, 1.0)
    task0 = _at(tasks, 0)

    # The batched and the unbatched functions compile in parallel (XLA's CPU compiler is single-threaded).
    with concurrent.futures.ThreadPoolExecutor(max_workers=1) as pool:
        batch_future = pool.submit(lambda: jax.block_until_ready(batched_jit(rngs, tasks, actions)))
        s0 = jax.block_until_ready(reset_jit(rngs[0], task0))
        traj = jax.block_until_ready(rollout_jit(s0, task0, actions[0]))
        batch = batch_future.result()
    return Rollouts(fam, reset_jit, rollout_jit, batched_jit, rngs, tasks, actions, s0, traj, batch)


_CACHE: dict[str, Rollouts] = {}


def _rollouts(name: str) -> Rollouts:
    if name not in _CACHE:
        _CACHE[name] = _build(name)
    return _CACHE[name]


@pytest.fixture(scope="module", autouse=True)
def optimised_programs():
    """This module's programs compiled fully optimised, as users run them (the suite turns most of XLA's
    optimisation off, conftest): MJX_TOL was measured so, and with optimisation off a different fusion of the same
    float operations, amplified by contacts, parts batched and unbatched Half-Cheetah rollouts by up to 0.2 after
    5 steps."""
    before = jax.config.read("jax_disable_most_optimizations")
    jax.config.update("jax_disable_most_optimizations", False)
    yield
    jax.config.update("jax_disable_most_optimizations", before)


@pytest.fixture(scope="module", params=FAMILIES)
def ro(request) -> Rollouts:
    return _rollouts(request.param)


@pytest.fixture(scope="module")
def ant_dir() -> Rollouts:
    return _rollouts("ant_dir")


@pytest.fixture(scope="module")
def ant_goal() -> Rollouts:
    return _rollouts("ant_goal")


# ------------------------------------------------------------------------------------ determinism, jit, vmap


def test_same_rng_gives_identical_states(ro):
    again = ro.reset(ro.rngs[0], ro.task(0))
    chex.assert_trees_all_equal(again, ro.s0)
    chex.assert_trees_all_equal(ro.rollout(again, ro.task(0), ro.actions[0]), ro.traj)
    chex.assert_trees_all_equal(ro.batched(ro.rngs, ro.tasks, ro.actions), ro.batch)
    # ...and the rng matters: another key gives another initial state.
    other = ro.reset(ro.rngs[1], ro.task(0))
    assert not np.allclose(other.obs, ro.s0.obs)


def _observable(state: envs.EnvState):
    """What the learner sees, plus the simulator's generalized coordinates and velocities."""
    coords = state.sim if isinstance(state.sim, (jax.Array, np.ndarray)) else (state.sim.q, state.sim.qd)
    return state.obs, state.reward, state.done, state.success, state.t, coords


def test_batched_rollout_matches_unbatched(ro):
    s0_batch, traj_batch = ro.batch
    chex.assert_shape(s0_batch.obs, (B, ro.fam.obs_size))
    chex.assert_shape(traj_batch.obs, (B, T, ro.fam.obs_size))
    chex.assert_shape([traj_batch.reward, traj_batch.done, traj_batch.success, traj_batch.t], (B, T))
    tol = EXACT_TOL if ro.fam.name == "point_goal" else MJX_TOL
    for i in range(B):
        s0 = ro.reset(ro.rngs[i], ro.task(i))
        traj = ro.rollout(s0, ro.task(i), ro.actions[i])
        chex.assert_trees_all_close(_np_at(s0_batch, i), s0, **EXACT_TOL)  # the whole state, simulator included
        chex.assert_trees_all_close(_observable(_np_at(traj_batch, i)), _observable(traj), **tol)
    # The comparison is not vacuous: the environments of the batch start apart, and running an environment
    # under its neighbour's task (tasks 0, 1, 2 point in nearly opposite directions) lands outside the tolerance.
    assert np.abs(s0_batch.obs[0] - s0_batch.obs[1]).max() > 1e-2
    for i in (0, 1):
        wrong = ro.rollout(_np_at(s0_batch, i), ro.task(i + 1), ro.actions[i])
        assert not np.allclose(wrong.reward, traj_batch.reward[i], **tol)


def test_step_counter_and_shapes(ro):
    chex.assert_shape(ro.s0.obs, (ro.fam.obs_size,))
    assert int(ro.s0.t) == 0 and float(ro.s0.reward) == 0.0 and float(ro.s0.done) == 0.0
    np.testing.assert_array_equal(ro.traj.t, np.arange(1, T + 1))
    chex.assert_shape(ro.traj.obs, (T, ro.fam.obs_size))
    assert np.all(np.isfinite(ro.traj.obs)) and np.all(np.isfinite(ro.traj.reward))
    np.testing.assert_array_equal(ro.traj.done, np.zeros(T))  # nobody terminates within T steps of reset
    assert not np.allclose(ro.traj.obs[-1], ro.s0.obs)  # the actions do move the system


def test_state_fed_back_does_not_retrace(ro):
    last = _at(ro.traj, -1)
    nxt = ro.rollout(last, ro.task(0), ro.actions[0])  # the guard raises on a retrace
    np.testing.assert_array_equal(nxt.t, np.arange(T + 1, 2 * T + 1))
    ro.reset(ro.rngs[2], ro.task(2))
    ro.batched(ro.rngs[::-1], ro.tasks, ro.actions)


def test_retrace_guard_is_armed(ro):
    """A rollout of another length must retrace, and the guard must catch it (so the test above can fail)."""
    with pytest.raises(AssertionError, match="traced > 1"):
        ro.rollout(ro.s0, ro.task(0), ro.actions[0, :2])


def _assert_strong_state(state: envs.EnvState):
    for path, leaf in jax.tree_util.tree_leaves_with_path(state):
        assert not leaf.weak_type, f"weak-typed leaf {jax.tree_util.keystr(path)}: {leaf}"
        # MJX keeps two boolean masks (eq_active, bvh_active) as uint8; nothing may be 64-bit.
        assert leaf.dtype in (jnp.float32, jnp.int32, jnp.uint8), (jax.tree_util.keystr(path), leaf.dtype)
    for field in (state.obs, state.reward, state.done, state.success):
        assert field.dtype == jnp.float32
    assert state.t.dtype == jnp.int32


def test_states_are_strongly_typed_float32_int32(ro):
    _assert_strong_state(ro.s0)
    _assert_strong_state(ro.traj)
    _assert_strong_state(ro.batch[0])
    _assert_strong_state(ro.batch[1])
    # The step function itself (not only the scan around it), at trace level: no compilation needed.
    _assert_strong_state(jax.eval_shape(ro.fam.step, ro.s0, ro.actions[0, 0], ro.task(0)))
    _assert_strong_state(jax.eval_shape(ro.fam.reset, ro.rngs[0], ro.task(0)))


def test_point_goal_eager_matches_jit():
    ro = _rollouts("point_goal")
    fam = ro.fam
    s = fam.reset(ro.rngs[0], ro.task(0))
    _assert_strong_state(s)
    chex.assert_trees_all_close(s, ro.s0)
    for k in range(T):
        s = fam.step(s, ro.actions[0, k], ro.task(0))
        _assert_strong_state(s)
        chex.assert_trees_all_close(s, _at(ro.traj, k), rtol=1e-6, atol=1e-6)


def test_rewards_match_formulas_on_simulated_states(ro):
    """The families wire the pure reward functions to the right simulator quantities."""
    prev = [ro.s0] + [_np_at(ro.traj, k) for k in range(T - 1)]
    for k in range(T):
        s0, s1, a, task = prev[k], _np_at(ro.traj, k), ro.actions[0, k], ro.task(0)
        name = ro.fam.name
        if name == "point_goal":
            reward, success = pg.reward_and_success(s1.sim, a, task)
            np.testing.assert_allclose(s1.sim, s0.sim + 0.1 * a, rtol=1e-6, atol=1e-6)
        elif name == "cheetah_vel":
            velocity = (s1.sim.q[0] - s0.sim.q[0]) / MJX_DT
            reward, success = mj.cheetah_reward_and_success(velocity, a, task)
        elif name == "ant_goal":
            reward, success = mj.ant_goal_reward_and_success(s1.sim.q[:2], a, task)
            np.testing.assert_allclose(s1.obs[:2], s1.sim.q[:2])  # the torso position is observed
        else:
            velocity = (s1.sim.q[:2] - s0.sim.q[:2]) / MJX_DT
            reward, success, done = mj.ant_dir_reward_and_success(velocity, s1.sim.q[2], a, task)
            assert float(done) == float(s1.done)
        np.testing.assert_allclose(s1.reward, reward, rtol=1e-4, atol=1e-4)
        assert float(s1.success) == float(success)


def test_actions_are_clipped(ro):
    big = 3.0 * ro.actions[0]
    assert np.any(np.abs(big) > 1.0)
    clipped = ro.rollout(ro.s0, ro.task(0), jnp.clip(big, -1.0, 1.0))
    chex.assert_trees_all_equal(ro.rollout(ro.s0, ro.task(0), big), clipped)
    assert not np.allclose(clipped.reward, ro.traj.reward)  # the clipped actions are other actions


def test_point_goal_action_clipping_by_hand():
    fam = envs.make("point_goal")
    task = envs.task_at(fam, 0)
    s = fam.reset(jax.random.key(3), task)
    five = fam.step(s, jnp.array([5.0, -7.0]), task)
    one = fam.step(s, jnp.array([1.0, -1.0]), task)
    chex.assert_trees_all_equal(five, one)
    np.testing.assert_allclose(one.sim, s.sim + jnp.array([0.1, -0.1]), atol=1e-7)
    half = fam.step(s, jnp.array([0.5, 0.0]), task)  # inside the box: not clipped
    np.testing.assert_allclose(half.sim, s.sim + jnp.array([0.05, 0.0]), atol=1e-7)
    np.testing.assert_allclose(one.reward, -jnp.linalg.norm(one.sim - task.goal) - 0.01 * 2.0, rtol=1e-6)


# ------------------------------------------------------------------------------------ termination


def test_ant_dir_terminated_state_is_absorbing(ant_dir):
    ro = ant_dir
    dead = ro.s0._replace(done=jnp.float32(1))
    traj = ro.rollout(dead, ro.task(0), ro.actions[0])
    for k in range(T):
        chex.assert_trees_all_equal(_np_at(traj.sim, k), dead.sim)
        np.testing.assert_array_equal(traj.obs[k], dead.obs)
    np.testing.assert_array_equal(traj.reward, np.zeros(T, np.float32))
    np.testing.assert_array_equal(traj.success, np.zeros(T, np.float32))
    np.testing.assert_array_equal(traj.done, np.ones(T, np.float32))
    np.testing.assert_array_equal(traj.t, np.arange(1, T + 1))
    # Without the flag the same actions move the ant and earn reward (so freezing is due to ``done``).
    assert not np.allclose(ro.traj.obs[0], ro.s0.obs)
    assert np.all(ro.traj.reward != 0)


def _lift_torso(state: envs.EnvState, z: float) -> envs.EnvState:
    sim = state.sim
    return state._replace(sim=sim.replace(qpos=sim.qpos.at[2].set(z), q=sim.q.at[2].set(z)))


def test_ant_dir_terminates_when_torso_too_high_then_freezes(ant_dir):
    ro = ant_dir
    traj = ro.rollout(_lift_torso(ro.s0, 1.5), ro.task(0), ro.actions[0])
    assert float(traj.sim.q[0, 2]) > 1.0
    np.testing.assert_array_equal(traj.done, np.ones(T, np.float32))  # terminates on the first step
    assert float(traj.reward[0]) != 0.0  # the terminating transition is still rewarded
    for k in range(1, T):  # then absorbing
        chex.assert_trees_all_equal(_np_at(traj.sim, k), _np_at(traj.sim, 0))
    np.testing.assert_array_equal(traj.reward[1:], np.zeros(T - 1, np.float32))
    np.testing.assert_array_equal(traj.success[1:], np.zeros(T - 1, np.float32))
    np.testing.assert_array_equal(traj.t, np.arange(1, T + 1))


def _move_torso(state: envs.EnvState, xy) -> envs.EnvState:
    sim = state.sim
    xy = jnp.asarray(xy, jnp.float32)
    return state._replace(sim=sim.replace(qpos=sim.qpos.at[:2].set(xy), q=sim.q.at[:2].set(xy)))


def test_ant_goal_oracle_at_the_goal_scores_above_the_threshold(ant_goal):
    # A policy that has reached the goal and stays there must score above the threshold: an Ant placed on its
    # goal (small random actions, it stays put) succeeds at every step, so its success rate is 1 >= 0.3.
    ro = ant_goal
    task = ro.task(0)
    traj = ro.rollout(_move_torso(ro.s0, task.goal), task, 0.1 * ro.actions[0])
    np.testing.assert_array_equal(traj.success, np.ones(T, np.float32))
    assert float(ro.fam.success_rate(traj.success[:, None])) >= ro.fam.success_threshold
    # ... and 0.6 m away (L1) from it, none.
    traj = ro.rollout(_move_torso(ro.s0, task.goal + jnp.asarray([0.6, 0.0])), task, 0.1 * ro.actions[0])
    np.testing.assert_array_equal(traj.success, np.zeros(T, np.float32))


def test_ant_goal_never_terminates(ant_goal):
    ro = ant_goal
    traj = ro.rollout(_lift_torso(ro.s0, 1.5), ro.task(0), ro.actions[0])
    assert float(traj.sim.q[0, 2]) > 1.0
    np.testing.assert_array_equal(traj.done, np.zeros(T, np.float32))
    assert not ro.fam.can_terminate and ro.fam.name == "ant_goal"


def test_success_rate_is_mean_over_all_steps():
    fam = envs.make("point_goal")
    success = jnp.array([[1.0, 0.0], [0.0, 0.0], [1.0, 1.0]], jnp.float32)
    np.testing.assert_allclose(fam.success_rate(success), 0.5)
    # A family that never terminates takes every step: the mask changes nothing.
    np.testing.assert_allclose(fam.success_rate(success, jnp.array([[1.0, 1.0], [1.0, 0.0], [0.0, 0.0]])), 0.5)


def test_ant_dir_success_rate_averages_over_the_steps_taken(ant_dir):
    # The paper averages "across all samples": an episode that fell has fewer samples, its absorbing steps after
    # the fall are none. A fall at the first step (the torso lifted out of range), succeeding there, beside an
    # episode that succeeds at each of its T steps: every sample succeeded.
    ro = ant_dir
    fell = ro.rollout(_lift_torso(ro.s0, 1.5), ro.task(0), ro.actions[0])
    np.testing.assert_array_equal(fell.done, np.ones(T, np.float32))
    taken = 1.0 - np.concatenate([[0.0], np.asarray(fell.done[:-1])])  # a step is taken from a live state
    np.testing.assert_array_equal(taken, np.eye(1, T)[0])
    success = jnp.stack([jnp.asarray(taken), jnp.ones(T)], axis=1)  # [T, 2]
    valid = jnp.stack([jnp.asarray(taken), jnp.ones(T)], axis=1)
    np.testing.assert_allclose(float(ro.fam.success_rate(success, valid)), 1.0)
    np.testing.assert_allclose(float(ro.fam.success_rate(success)), (1 + T) / (2 * T))  # counting every step
    # The rollouts the methods learn from carry that mask (``Trajectory.valid``) and pass it.
    half = success.at[:, 1].set(jnp.arange(T) % 2 == 0)
    np.testing.assert_allclose(float(ro.fam.success_rate(half, valid)), (1 + -(-T // 2)) / (1 + T), rtol=1e-6)


# ------------------------------------------------------------------------------------ reward formulas

ACT6 = np.array([0.5, -1.0, 0.0, 0.2, 0.3, -0.4], np.float32)  # Σa² = 1.54
ACT8 = np.array([0.5, -1.0, 0.0, 0.2, 0.3, -0.4, 1.0, 0.1], np.float32)  # Σa² = 2.55


def _cheetah(v, goal, action=ACT6):
    r, s = mj.cheetah_reward_and_success(jnp.float32(v), jnp.asarray(action), mj.CheetahVelTask(jnp.float32(goal)))
    return float(r), float(s)


def test_cheetah_at_goal_velocity_succeeds_and_pays_only_control():
    for goal in (1.4, -2.66, 0.0, 2.8):
        reward, success = _cheetah(goal, goal)
        assert success == 1.0
        np.testing.assert_allclose(reward, -0.05 * 1.54, rtol=1e-6)
    assert _cheetah(1.4, 1.4, np.zeros(6, np.float32))[0] == 0.0


@pytest.mark.parametrize(
    "goal, v, expected",
    [
        # v_g = 0: the 0.1 m/s floor.
        (0.0, 0.0, 1.0), (0.0, 0.09, 1.0), (0.0, -0.09, 1.0), (0.0, 0.11, 0.0), (0.0, -0.11, 0.0),
        # |v - v_g| < 0.3·|v_g| = 0.6, both sides of the goal, both signs of it.
        (2.0, 2.59, 1.0), (2.0, 2.61, 0.0), (2.0, 1.41, 1.0), (2.0, 1.39, 0.0),
        (-2.0, -2.59, 1.0), (-2.0, -2.61, 0.0), (-2.0, -1.41, 1.0), (-2.0, -1.39, 0.0),
        # Small goals: 0.3·|v_g| < 0.1, so the floor applies.
        (0.2, 0.29, 1.0), (0.2, 0.31, 0.0), (-0.14, -0.05, 1.0), (-0.14, -0.25, 0.0),
        # The wrong direction at the right speed fails.
        (1.4, -1.4, 0.0),
    ],
)
def test_cheetah_success_boundary(goal, v, expected):
    reward, success = _cheetah(v, goal)
    assert success == expected
    np.testing.assert_allclose(reward, -abs(v - goal) - 0.05 * 1.54, rtol=1e-5)


@given(
    goal=st.floats(-3.0, 3.0, width=32),
    v=st.floats(-4.0, 4.0, width=32),
    action=hnp.arrays(np.float32, 6, elements=st.floats(-1.0, 1.0, width=32)),
)
def test_cheetah_formula_property(goal, v, action):
    err = abs(float(v) - float(goal))
    tol = max(0.3 * abs(float(goal)), 0.1)
    assume(abs(err - tol) > 1e-4)  # float32 rounding can decide the exact boundary either way
    reward, success = _cheetah(v, goal, action)
    assert success == float(err < tol)
    np.testing.assert_allclose(reward, -err - 0.05 * np.sum(np.square(action, dtype=np.float64)), rtol=1e-5,
                               atol=1e-5)


def _ant_goal(xy, goal, action=ACT8):
    task = mj.AntGoalTask(jnp.asarray(goal, jnp.float32))
    r, s = mj.ant_goal_reward_and_success(jnp.asarray(xy, jnp.float32), jnp.asarray(action), task)
    return float(r), float(s)


@pytest.mark.parametrize(
    "xy, expected",
    [
        ((0.0, 3.0), 1.0),
        ((0.2, 3.2), 1.0),  # L1 0.4
        ((0.0, 3.49), 1.0),
        ((-0.24, 2.75), 1.0),  # L1 0.49
        ((0.3, 3.3), 0.0),  # L1 0.6 (the L2 distance, 0.42, would pass: the ball is L1)
        ((0.0, 2.49), 0.0),
        ((0.0, -3.0), 0.0),
    ],
)
def test_ant_goal_l1_ball(xy, expected):
    goal = (0.0, 3.0)
    reward, success = _ant_goal(xy, goal)
    assert success == expected
    l1 = abs(xy[0] - goal[0]) + abs(xy[1] - goal[1])
    np.testing.assert_allclose(reward, -l1 - 0.01 * 2.55, rtol=1e-5, atol=1e-6)


@given(
    offset=hnp.arrays(np.float32, 2, elements=st.floats(-0.75, 0.75, width=32)),  # around the ball's rim
    angle=st.floats(-360.0, 360.0, width=32),
    action=hnp.arrays(np.float32, 8, elements=st.floats(-1.0, 1.0, width=32)),
)
def test_ant_goal_formula_property(offset, angle, action):
    goal = np.asarray(envs.make("ant_goal").tasks([angle]).goal[0], np.float64)
    np.testing.assert_allclose(np.linalg.norm(goal), 3.0, rtol=1e-5)
    xy = (goal + offset).astype(np.float32)
    l1 = float(np.sum(np.abs(xy.astype(np.float64) - goal)))
    assume(abs(l1 - 0.5) > 1e-4)
    reward, success = _ant_goal(xy, goal, action)
    assert success == float(l1 < 0.5)
    np.testing.assert_allclose(reward, -l1 - 0.01 * np.sum(np.square(action, dtype=np.float64)), rtol=1e-5,
                               atol=1e-5)


def _ant_dir(v, direction, z=0.6, action=ACT8):
    task = mj.AntDirTask(jnp.asarray(direction, jnp.float32))
    r, s, d = mj.ant_dir_reward_and_success(jnp.asarray(v, jnp.float32), jnp.float32(z), jnp.asarray(action), task)
    return float(r), float(s), float(d)


@pytest.mark.parametrize(
    "v, expected",
    [
        ((1.0, 0.0), 1.0),
        ((0.6, 0.2), 1.0),  # ‖v̂ − d‖ = 0.32
        ((0.51, 0.0), 1.0),
        ((0.49, 0.0), 0.0),  # right direction, too slow
        ((0.4, 0.05), 0.0),
        ((0.6, 0.3), 0.0),  # fast enough, ‖v̂ − d‖ = 0.46
        ((-1.0, 0.0), 0.0),
        ((0.0, 2.0), 0.0),
        ((0.0, 0.0), 0.0),  # standing still: no NaN, no success
    ],
)
def test_ant_dir_success_needs_direction_and_speed(v, expected):
    reward, success, done = _ant_dir(v, (1.0, 0.0))
    assert success == expected
    assert done == 0.0
    np.testing.assert_allclose(reward, v[0] + 1.0 - 0.05 * 2.55, rtol=1e-5, atol=1e-6)


def test_ant_dir_reward_projects_velocity_on_direction():
    reward, _, _ = _ant_dir((2.0, 1.0), (0.0, 1.0))
    np.testing.assert_allclose(reward, 1.0 + 1.0 - 0.05 * 2.55, rtol=1e-6)
    reward, _, _ = _ant_dir((2.0, 1.0), (0.0, 1.0), action=np.zeros(8, np.float32))
    assert reward == 2.0


@pytest.mark.parametrize("z, expected", [(0.19, 1.0), (0.21, 0.0), (0.55, 0.0), (0.99, 0.0), (1.01, 1.0),
                                         (-0.5, 1.0), (3.0, 1.0)])
def test_ant_dir_termination_height(z, expected):
    assert _ant_dir((1.0, 0.0), (1.0, 0.0), z=z)[2] == expected


@given(
    speed=st.floats(0.0, 2.0),
    heading=st.floats(-60.0, 60.0),  # degrees off the goal direction; the 0.4 chord is at about 23 degrees
    angle=st.floats(-360.0, 360.0, width=32),
    z=st.floats(-1.0, 2.0, width=32),
    action=hnp.arrays(np.float32, 8, elements=st.floats(-1.0, 1.0, width=32)),
)
def test_ant_dir_formula_property(speed, heading, angle, z, action):
    d = np.asarray(envs.make("ant_dir").tasks([angle]).direction[0], np.float64)
    np.testing.assert_allclose(np.linalg.norm(d), 1.0, rtol=1e-5)
    rad = np.deg2rad(float(angle) + heading)
    v = (speed * np.array([np.cos(rad), np.sin(rad)])).astype(np.float32)
    v64 = v.astype(np.float64)
    speed = float(np.linalg.norm(v64))
    assume(abs(speed - 0.5) > 1e-3 and abs(float(z) - 0.2) > 1e-4 and abs(float(z) - 1.0) > 1e-4)
    off = float(np.linalg.norm(v64 / speed - d)) if speed > 0 else 1.0
    assume(abs(off - 0.4) > 1e-3)
    reward, success, done = _ant_dir(v, d, z, action)
    assert success == float(off < 0.4 and speed > 0.5)
    assert done == float(z < 0.2 or z > 1.0)
    expected = float(v64 @ d) + 1.0 - 0.05 * np.sum(np.square(action, dtype=np.float64))
    np.testing.assert_allclose(reward, expected, rtol=1e-5, atol=1e-5)


def _point(pos, goal, action=np.array([0.6, -0.8], np.float32)):  # Σa² = 1
    r, s = pg.reward_and_success(jnp.asarray(pos, jnp.float32), jnp.asarray(action),
                                 pg.PointGoalTask(jnp.asarray(goal, jnp.float32)))
    return float(r), float(s)


@pytest.mark.parametrize(
    "pos, expected",
    [((2.0, 0.0), 1.0), ((1.81, 0.0), 1.0), ((2.0, 0.19), 1.0), ((1.79, 0.0), 0.0),
     ((2.15, 0.15), 0.0),  # L2 0.212 (L∞ 0.15 would pass: the ball is Euclidean)
     ((0.0, 0.0), 0.0)],
)
def test_point_goal_success_radius(pos, expected):
    goal = (2.0, 0.0)
    reward, success = _point(pos, goal)
    assert success == expected
    np.testing.assert_allclose(reward, -np.hypot(pos[0] - goal[0], pos[1] - goal[1]) - 0.01, rtol=1e-5, atol=1e-6)


@given(
    offset=hnp.arrays(np.float32, 2, elements=st.floats(-0.25, 0.25, width=32)),  # around the ball's rim
    angle=st.floats(-360.0, 360.0, width=32),
)
def test_point_goal_formula_property(offset, angle):
    goal = np.asarray(envs.make("point_goal").tasks([angle]).goal[0], np.float64)
    np.testing.assert_allclose(np.linalg.norm(goal), 2.0, rtol=1e-5)
    pos = (goal + offset).astype(np.float32)
    dist = float(np.linalg.norm(pos.astype(np.float64) - goal))
    assume(abs(dist - 0.2) > 1e-4)
    reward, success = _point(pos, goal)
    assert success == float(dist < 0.2)
    np.testing.assert_allclose(reward, -dist - 0.01, rtol=1e-5, atol=1e-5)


# ------------------------------------------------------------------------------------ sequences


@pytest.mark.parametrize("name", FAMILIES)
def test_non_stationary_sequence_is_the_papers(name):
    expected = np.asarray(PAPER_VALUES[name], np.float32)
    assert len(expected) == 40 and len(set(expected.tolist())) == 40
    values = envs.sequence_values(name, "non-stationary")
    assert values.dtype == np.float32
    np.testing.assert_array_equal(values, expected)
    np.testing.assert_array_equal(envs.sequence_values(name), expected)  # the default kind
    np.testing.assert_array_equal(envs.sequence_values(name, "non-stationary", seed=7), expected)  # seedless
    np.testing.assert_array_equal(envs.sequence_values(name, num_tasks=7), expected[:7])
    np.testing.assert_array_equal(envs.make(name).task_values, PAPER_VALUES[name])  # as Python floats


@pytest.mark.parametrize("name", FAMILIES)
def test_stationary_sequence_is_a_seeded_permutation(name):
    expected = np.asarray(PAPER_VALUES[name], np.float32)
    a = envs.sequence_values(name, "stationary", seed=0)
    np.testing.assert_array_equal(np.sort(a), np.sort(expected))
    np.testing.assert_array_equal(envs.sequence_values(name, "stationary", seed=0), a)
    assert not np.array_equal(a, expected)
    orders = {tuple(envs.sequence_values(name, "stationary", seed=s).tolist()) for s in range(5)}
    assert len(orders) == 5
    np.testing.assert_array_equal(envs.sequence_values(name, "stationary", seed=0, num_tasks=5), a[:5])


@given(seed=st.integers(0, 2**32 - 1))
def test_stationary_permutation_property(seed):
    a = envs.sequence_values("point_goal", "stationary", seed=seed)
    np.testing.assert_array_equal(np.sort(a), np.sort(np.asarray(ANT_ANGLES_DEG, np.float32)))
    np.testing.assert_array_equal(envs.sequence_values("point_goal", "stationary", seed=seed), a)


def _task_matrix(tasks) -> np.ndarray:
    leaves = jax.tree.leaves(tasks)
    n = leaves[0].shape[0]
    return np.concatenate([np.asarray(x, np.float64).reshape(n, -1) for x in leaves], axis=1)


@pytest.mark.parametrize("name", FAMILIES)
def test_held_out_tasks_are_disjoint_from_training(name):
    fam = envs.make(name)
    held, train = np.asarray(fam.held_out_values), np.asarray(PAPER_VALUES[name])
    assert len(held) > 0
    assert not set(held.tolist()) & set(train.tolist())
    # Disjoint as tasks too (angles 180 and -180 are the same task): compare the task pytrees.
    held_tasks, train_tasks = _task_matrix(envs.held_out(fam)), _task_matrix(envs.sequence(fam))
    assert held_tasks.shape[0] == len(held) and train_tasks.shape[0] == 40
    gaps = np.linalg.norm(held_tasks[:, None, :] - train_tasks[None, :, :], axis=-1)
    assert gaps.min() > 1e-3


def test_task_geometry():
    goal = envs.task_at("ant_goal", ANT_ANGLES_DEG.index(90)).goal
    chex.assert_shape(goal, (2,))
    np.testing.assert_allclose(goal, [0.0, 3.0], atol=1e-5)
    direction = envs.task_at("ant_dir", ANT_ANGLES_DEG.index(0)).direction
    np.testing.assert_allclose(direction, [1.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(envs.task_at("ant_dir", ANT_ANGLES_DEG.index(90)).direction, [0.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(envs.task_at("ant_goal", ANT_ANGLES_DEG.index(180)).goal, [-3.0, 0.0], atol=1e-5)
    np.testing.assert_allclose(envs.task_at("point_goal", ANT_ANGLES_DEG.index(-90)).goal, [0.0, -2.0], atol=1e-5)
    velocity = envs.task_at("cheetah_vel", 39).velocity
    assert velocity.shape == () and velocity.dtype == jnp.float32 and float(velocity) == np.float32(2.8)


@pytest.mark.parametrize("name", FAMILIES)
def test_task_at_is_the_sequence_entry(name):
    for kind, seed in (("non-stationary", 0), ("stationary", 3)):
        stacked = envs.sequence(name, kind, seed=seed)
        for i in (0, 17, 39):
            chex.assert_trees_all_equal(envs.task_at(name, i, kind, seed=seed), _at(stacked, i))


# ------------------------------------------------------------------------------------ bad inputs


def test_unknown_family_lists_the_allowed_names():
    with pytest.raises(ValueError, match=re.escape("allowed: point_goal, cheetah_vel, ant_goal, ant_dir")):
        envs.make("half_cheetah")
    with pytest.raises(ValueError, match="'humanoid'"):
        envs.sequence_values("humanoid")


def test_unknown_sequence_kind_lists_the_allowed_kinds():
    with pytest.raises(ValueError, match=re.escape("'shuffled'; allowed: stationary, non-stationary")):
        envs.sequence_values("point_goal", "shuffled")
    with pytest.raises(ValueError, match="allowed: stationary, non-stationary"):
        envs.sequence("cheetah_vel", "nonstationary")


@pytest.mark.parametrize("num_tasks", [0, 41, -1, 2.5, "3", True])
@pytest.mark.parametrize("name", ["point_goal", "cheetah_vel"])
def test_bad_num_tasks(name, num_tasks):
    with pytest.raises(ValueError, match=re.escape("num_tasks must be an integer in [1, 40]")):
        envs.sequence_values(name, num_tasks=num_tasks)
    with pytest.raises(ValueError, match=re.escape("num_tasks must be an integer in [1, 40]")):
        envs.sequence(name, "stationary", num_tasks=num_tasks)


def test_good_num_tasks_bounds():
    family = envs.make("point_goal")
    full = np.asarray(family.task_values, np.float32)
    # num_tasks takes a prefix of the paper's order, at both ends of its range and as a NumPy integer
    np.testing.assert_array_equal(envs.sequence_values("point_goal", num_tasks=1), full[:1])
    np.testing.assert_array_equal(envs.sequence_values("point_goal", num_tasks=np.int64(40)), full)
    np.testing.assert_array_equal(envs.sequence_values("point_goal", num_tasks=7), full[:7])
    # the stationary sequence is the whole list shuffled by the seed, then the prefix
    shuffled = envs.sequence_values("point_goal", "stationary", seed=3)
    assert sorted(shuffled.tolist()) == sorted(full.tolist()) and not np.array_equal(shuffled, full)
    np.testing.assert_array_equal(envs.sequence_values("point_goal", "stationary", seed=3, num_tasks=5), shuffled[:5])


@pytest.mark.parametrize("index", [-1, 40, 1.5, True])
def test_bad_task_index(index):
    with pytest.raises(IndexError, match=re.escape("task index must be an integer in [0, 39]")):
        envs.task_at("ant_dir", index)


@pytest.mark.parametrize(
    "name, values, message",
    [
        ("point_goal", [[0.0, 90.0]], "non-empty 1-D list"),
        ("point_goal", [[0.0], [90.0]], "non-empty 1-D list"),
        ("point_goal", [], "non-empty 1-D list"),
        ("point_goal", 90.0, "non-empty 1-D list"),
        ("point_goal", ["north"], "1-D list of numbers"),
        ("ant_goal", [0.0, "east"], "1-D list of numbers"),
        ("point_goal", ["90"], "1-D list of numbers"),  # numeric-looking strings are not numbers
        ("cheetah_vel", [True], "1-D list of numbers"),
        ("ant_dir", [[0.0, 9.0], [18.0]], "1-D list of numbers"),  # ragged
        ("ant_dir", [float("nan")], "finite number in"),
        ("ant_goal", [0.0, float("inf")], "finite number in"),
        ("cheetah_vel", [5.0], re.escape("goal velocity in m/s must be a finite number in [-3.0, 3.0]")),
        ("cheetah_vel", [0.5, -3.01], re.escape("[-3.0, 3.0]")),
        ("ant_dir", [400.0], re.escape("[-360.0, 360.0]")),
    ],
)
def test_malformed_task_lists(name, values, message):
    fam = envs.make(name)
    with pytest.raises(ValueError, match=message) as info:
        fam.tasks(values)
    assert name in str(info.value)


def test_well_formed_task_lists():
    tasks = envs.make("cheetah_vel").tasks([-3.0, 0.0, 3.0])
    assert tasks.velocity.dtype == jnp.float32
    np.testing.assert_array_equal(tasks.velocity, [-3.0, 0.0, 3.0])
    chex.assert_shape(envs.make("ant_goal").tasks((0, 90)).goal, (2, 2))
