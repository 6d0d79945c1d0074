"""Tests of the method interface and the continual loop (lax.scan over tasks, vmap over seeds)."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jcomps import continual, envs, methods
from jcomps.methods import ppo_tl
from jcomps.training import ppo

SMALL = ppo_tl.PPOTLConfig(ppo=ppo.PPOConfig(num_trajectories=4, num_updates=2, minibatch_size=32,
                                             hidden_sizes=(16,), budget=3))


@pytest.fixture(scope="module")
def family():
    return envs.make("point_goal")


def test_learn_task_traced_once_however_long_the_sequence(family):
    method = methods.make("ppo_tl", family, SMALL)
    counted = chex.assert_max_traces(method.learn_task, n=1)
    method = method._replace(learn_task=counted)
    for num_tasks in (1, 3, 5):
        _, metrics = continual.run_sequence(method, envs.sequence(family, num_tasks=num_tasks),
                                            jax.random.PRNGKey(0))
        chex.assert_shape(metrics.iterations, (num_tasks,))
        chex.assert_shape(metrics.per_iteration.mean_return, (num_tasks, 3))
    chex.clear_trace_counter()


def test_seeds_vmap_matches_single_runs(family):
    method = methods.make("ppo_tl", family, SMALL)
    tasks = envs.sequence(family, num_tasks=2)
    rngs = jax.random.split(jax.random.PRNGKey(3), 2)
    states, batched = continual.run_seeds(method, tasks, rngs)
    for s in range(2):
        _, single = jax.jit(lambda r: continual.run_sequence(method, tasks, r))(rngs[s])
        chex.assert_trees_all_close(jax.tree.map(lambda x: x[s], batched), single, rtol=1e-4, atol=1e-4)
    np.testing.assert_array_equal(np.asarray(states.task_index), [2, 2])


def test_parameters_carry_over_between_tasks(family):
    method = methods.make("ppo_tl", family, SMALL)
    state = method.init(jax.random.PRNGKey(0))
    task = envs.task_at(family, 0)
    after, _ = jax.jit(method.learn_task)(state, task)
    assert int(after.task_index) == 1
    # learn_task starts from the carried parameters: learning the next task from `after` differs from learning it
    # from the initial parameters with the same rng.
    nxt = envs.task_at(family, 1)
    a, _ = jax.jit(method.learn_task)(after, nxt)
    b, _ = jax.jit(method.learn_task)(after._replace(params=state.params), nxt)
    assert not np.allclose(np.asarray(a.params.value[0]["w"]), np.asarray(b.params.value[0]["w"]))


def test_per_seed_task_orders(family):
    method = methods.make("ppo_tl", family, SMALL)
    values = np.stack([envs.sequence_values(family, "stationary", s, 2) for s in (0, 1)])
    assert not np.array_equal(values[0], values[1])
    tasks = jax.tree.map(lambda x: x.reshape((2, 2) + x.shape[1:]), family.tasks(values.reshape(-1)))
    _, metrics = continual.run_seeds(method, tasks, jax.random.split(jax.random.PRNGKey(0), 2), tasks_per_seed=True)
    chex.assert_shape(metrics.iterations, (2, 2))


def test_unknown_method_and_wrong_config():
    family = envs.make("point_goal")
    with pytest.raises(ValueError, match="unknown method .nope.; allowed: ppo_tl, ppo, comps, gmps, gmps_ppo, "):
        methods.make("nope", family)
    with pytest.raises(TypeError, match="PPOTLConfig"):
        methods.make("ppo_tl", family, ppo.PPOConfig())


def test_a_method_that_never_changes_its_policy_forgets_nothing(family):
    """The learnt tasks' evaluations (right after each task in ``evaluate_task``, at the end in ``learnt_tasks``) use
    the same episodes of each task, so a method whose learning leaves the policy as it was scores exactly the same
    both times: zero forgetting, not zero on average."""
    from jcomps.analysis import continual_metrics

    method = methods.make("ppo_tl", family, SMALL)
    state = method.init(jax.random.PRNGKey(0))
    seq = envs.sequence(family, num_tasks=3)
    shapes = jax.eval_shape(method.learn_task, state, envs.task_at(family, 0))[1]

    def frozen(state, task):  # counts the task and learns nothing
        del task
        return state._replace(task_index=state.task_index + 1), jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype),
                                                                             shapes)

    method = method._replace(learn_task=frozen)
    config = continual.EvalConfig(backward_tasks=1, learnt_episodes=3)
    key = jax.random.PRNGKey(7)
    learn = jax.jit(lambda s, i: continual.learn_at(method, s, seq, i))
    evaluate_task = jax.jit(lambda s, i: continual.evaluate_task(method, config, s, seq, i, key))
    end, per_task = state, []
    for i in range(3):  # as the runner's chunk of three tasks
        end, metrics = learn(end, i)
        per_task.append(continual.chunk_metrics(metrics, evaluate_task(end, i)))
    chunk = jax.tree.map(lambda *x: jnp.stack(x), *per_task)
    evaluate = jax.jit(lambda s, n: continual.learnt_tasks(method, config, s, seq, n, key))
    final = evaluate(end, 3)
    chex.assert_shape(final.mean_return, (3,))
    np.testing.assert_array_equal(np.asarray(final.valid), True)
    np.testing.assert_array_equal(np.asarray(final.mean_return), np.asarray(chunk.learnt.mean_return))
    assert len(set(np.asarray(final.mean_return).tolist())) == 3  # three tasks' own episodes, not one stream
    f = continual_metrics.forgetting(chunk.learnt.success_rate, final.success_rate, final.valid & chunk.learnt.valid)
    np.testing.assert_array_equal(f, 0.0)
    # The backward evaluation of task i − 1 after task i has its own episodes; its success rate comes with it.
    chex.assert_shape(chunk.backward_success, (3, 1))
    # Tasks not yet learnt are skipped: zeros, not valid.
    two = evaluate(end, 2)
    np.testing.assert_array_equal(np.asarray(two.valid), [True, True, False])
    np.testing.assert_array_equal(np.asarray(two.mean_return)[:2], np.asarray(final.mean_return)[:2])
    assert float(two.mean_return[2]) == 0.0 and float(two.success_rate[2]) == 0.0
