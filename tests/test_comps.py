"""Tests of the CoMPS and GMPS+PPO methods on tiny Point Goal settings."""

import chex
import jax
import numpy as np
import pytest

from jcomps import continual, envs, meta, methods, ppo
from jcomps.methods import comps

SMALL_PPO = ppo.PPOConfig(num_trajectories=4, num_updates=2, minibatch_size=32, hidden_sizes=(16,), budget=3)
SMALL_META = meta.MetaConfig(num_meta_steps=2, num_outer_steps=1, inner_trajectories=2, skilled_trajectories=2)


@pytest.fixture(scope="module")
def run():
    family = envs.make("point_goal")
    config = comps.CoMPSConfig(ppo=SMALL_PPO, meta=SMALL_META, max_tasks=3, num_skilled=3, num_offpolicy=5)
    method = methods.make("comps", family, config)
    state0 = method.init(jax.random.PRNGKey(0))
    learn = jax.jit(chex.assert_max_traces(method.learn_task, n=1))
    s1, m1 = learn(state0, envs.task_at(family, 0))
    s2, m2 = learn(s1, envs.task_at(family, 1))
    return method, state0, s1, s2, (m1, m2)


def test_stores_fill_one_slot_per_task(run):
    _, state0, s1, s2, _ = run
    np.testing.assert_array_equal(state0.stores.task_valid, [False, False, False])
    np.testing.assert_array_equal(s1.stores.task_valid, [True, False, False])
    np.testing.assert_array_equal(s2.stores.task_valid, [True, True, False])
    assert int(s2.task_index) == 2
    # D*_0 holds 3 real trajectories (finite returns, sorted high to low); D_0 has 5 rows, all filled by
    # min(M, ceil(0.05 * 3)) = 1 iteration of 4 trajectories at most: 4 valid rows.
    returns = np.asarray(s1.stores.skilled.returns[0])
    assert np.all(np.isfinite(returns)) and np.all(np.diff(returns) <= 0)
    assert float(np.sum(s1.stores.offpolicy.mask[0])) == 4.0
    np.testing.assert_array_equal(s1.stores.offpolicy.mask[1:], 0)


def test_the_meta_step_produces_the_next_tasks_policy(run):
    _, state0, s1, _, _ = run
    chex.assert_trees_all_equal(s1.params.policy, s1.meta.policy)
    w0, w1 = state0.params.policy["mean"][0]["w"], s1.params.policy["mean"][0]["w"]
    assert not np.allclose(np.asarray(w1), np.asarray(w0))


def test_metrics_have_the_shared_shape(run):
    _, _, _, _, (m1, m2) = run
    chex.assert_shape(m1.per_iteration.success_rate, (3,))
    assert 1 <= int(m1.iterations) <= 3


def test_gmps_ppo_is_registered_without_importance_weights():
    method = methods.make("gmps_ppo", envs.make("point_goal"))
    assert method.name == "gmps_ppo"
    assert not method.config.meta.importance_sampling and not method.config.meta.vtrace_baseline
    assert methods.make("comps", envs.make("point_goal")).config.meta.importance_sampling


def test_comps_in_the_continual_loop():
    family = envs.make("point_goal")
    config = comps.CoMPSConfig(ppo=SMALL_PPO, meta=SMALL_META, max_tasks=2, num_skilled=2, num_offpolicy=3)
    _, metrics = continual.run_seeds(methods.make("comps", family, config), envs.sequence(family, num_tasks=2),
                                     jax.random.split(jax.random.PRNGKey(0), 2))
    chex.assert_shape(metrics.iterations, (2, 2))


def test_learning_past_max_tasks_is_refused():
    family = envs.make("point_goal")
    config = comps.CoMPSConfig(ppo=SMALL_PPO, meta=SMALL_META, max_tasks=2, num_skilled=2, num_offpolicy=3)
    method = methods.make("comps", family, config)
    with pytest.raises(ValueError, match="max_tasks=2"):
        continual.run_sequence(method, envs.sequence(family, num_tasks=3), jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="max_tasks=2"):
        continual.run_chunk(method, continual.EvalConfig(), method.init(jax.random.PRNGKey(0)),
                            envs.sequence(family, num_tasks=3), 0, 1, jax.random.PRNGKey(1))
    full = method.init(jax.random.PRNGKey(0))._replace(task_index=jax.numpy.int32(2))
    with pytest.raises(ValueError, match="past max_tasks=2"):
        method.learn_task(full, envs.task_at(family, 0))
