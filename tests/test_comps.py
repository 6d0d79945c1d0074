"""Tests of the CoMPS and GMPS+PPO methods on tiny Point Goal settings."""

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jcomps import configs, continual, envs, methods
from jcomps.methods import comps
from jcomps.training import meta, networks, ppo

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


def test_metrics_are_the_rl_steps_iterations(run):
    _, _, _, _, (m1, m2) = run
    for m in (m1, m2):  # one entry per budgeted iteration, valid for those that ran
        chex.assert_shape(m.per_iteration.success_rate, (3,))
        its = int(m.iterations)
        assert 1 <= its <= 3 and bool(m.solved) == (its < 3 or float(m.per_iteration.success_rate[2]) >= 0.7)
        np.testing.assert_array_equal(m.per_iteration.valid, np.arange(3) < its)


def test_the_meta_phase_reports_its_health(run):
    _, _, _, _, (m1, m2) = run
    chex.assert_shape(m1.meta.steps.bc_loss, (SMALL_META.num_meta_steps * SMALL_META.num_outer_steps,))
    for m, seen in ((m1, 1), (m2, 2)):
        for stats in (m.meta.start, m.meta.end):
            chex.assert_shape(stats.value_ev, (3,))
            assert np.all(np.isfinite(np.asarray(stats.value_ev)[:seen]))
            assert np.all(np.isnan(np.asarray(stats.value_ev)[seen:]))  # slots not learnt yet
            assert np.all((np.asarray(stats.rho)[:seen] > 0) & (np.asarray(stats.rho)[:seen] <= 1))


def test_a_new_tasks_head_starts_from_the_rl_steps_value_function_then_fits_its_returns():
    family = envs.make("point_goal")
    no_meta = dataclasses.replace(SMALL_META, num_meta_steps=0, value_fit_steps=0)
    config = comps.CoMPSConfig(ppo=SMALL_PPO, meta=no_meta, max_tasks=3, num_skilled=3, num_offpolicy=5)
    state0 = methods.make("comps", family, config).init(jax.random.PRNGKey(0))

    def learn(**meta_fields):
        cfg = dataclasses.replace(config, meta=dataclasses.replace(no_meta, **meta_fields))
        return jax.jit(methods.make("comps", family, cfg).learn_task)(state0, envs.task_at(family, 0))

    s1, m1 = learn()
    # No fit, no meta steps: head 0 is the critic the RL step trained (kept in params.value), the others untouched.
    chex.assert_trees_all_equal(meta.head_params(s1.meta.value, 0), s1.params.value)
    chex.assert_trees_all_equal(meta.head_params(s1.meta.value, 1), meta.head_params(state0.meta.value, 1))
    chex.assert_trees_all_equal(m1.meta.start, m1.meta.end)
    s1r, _ = learn(value_init="random")
    chex.assert_trees_all_equal(s1r.meta.value, state0.meta.value)
    # The same RL step and stores, then a fit to D_0's returns (meta.fit_head, whose law is tested in
    # test_meta): head 0 alone moves, and explains more of them.
    s1f, m1f = learn(value_fit_steps=50)
    chex.assert_trees_all_equal(s1f.stores, s1.stores)
    assert float(m1f.meta.start.value_l2[0]) < float(m1.meta.start.value_l2[0])
    assert float(m1f.meta.start.value_ev[0]) > float(m1.meta.start.value_ev[0])
    chex.assert_trees_all_equal(meta.head_params(s1f.meta.value, 1), meta.head_params(state0.meta.value, 1))


def test_the_meta_step_works_in_the_rl_steps_reward_units_and_learning_rate():
    for family in ("cheetah_vel", "ant_goal", "point_goal"):
        config = methods.default_config("comps", family)
        assert config.meta.reward_scale is None and config.meta.value_learning_rate is None
        resolved = comps.meta_config(config)
        assert resolved.reward_scale == config.ppo.reward_scale
        assert resolved.value_learning_rate == config.ppo.learning_rate
    config = methods.default_config("comps", "ant_goal")
    fixed = dataclasses.replace(config, meta=dataclasses.replace(config.meta, reward_scale=1.0,
                                                                 value_learning_rate=1e-3))
    assert comps.meta_config(fixed).reward_scale == 1.0 and comps.meta_config(fixed).value_learning_rate == 1e-3


def test_point_goals_inner_step_is_the_papers_in_raw_reward_units():
    """The meta step's advantages are in its reward units (the RL step's, Point Goal's 0.1 since issue 44, and 0.1
    too for GMPS, whose RL step is calibrated at 1): they and the inner learning rate multiply to the paper's
    α = 0.005 on raw rewards, for every rung."""
    for name in ("comps", "gmps", "gmps_ppo", "gmps_ppo_is", "gmps_ppo_is_x2"):
        config = methods.default_config(name, "point_goal")
        assert config.meta.inner_learning_rate * comps.meta_config(config).reward_scale == pytest.approx(0.005)


def test_gmps_takes_its_own_calibration_on_point_goal_only():
    """GMPS's vanilla policy gradient is calibrated on Point Goal (reward scale 1, learning rate 3e-3,
    docs/families.md); on the other families, and for every other rung, the family's PPO settings hold."""
    gmps, ppo_rung = methods.default_config("gmps", "point_goal"), methods.default_config("gmps_ppo", "point_goal")
    assert (gmps.ppo.reward_scale, gmps.ppo.learning_rate) == (1.0, 3e-3)
    assert gmps.ppo.surrogate == "vanilla" and gmps.ppo.num_updates == 1
    assert (ppo_rung.ppo.reward_scale, ppo_rung.meta.inner_learning_rate) == (0.1, 0.05)
    # Its meta step keeps the other rungs' reward units, so a copy of its critic (trained at scale 1) cannot start
    # a head.
    resolved, other = comps.meta_config(gmps), comps.meta_config(ppo_rung)
    assert (resolved.reward_scale, resolved.inner_learning_rate) == (other.reward_scale, other.inner_learning_rate)
    assert (gmps.meta.value_init, ppo_rung.meta.value_init) == ("random", "rl_step")
    for family in ("cheetah_vel", "ant_dir"):
        a, b = methods.default_config("gmps", family), methods.default_config("gmps_ppo", family)
        assert (a.ppo.reward_scale, a.ppo.learning_rate, a.meta) == (b.ppo.reward_scale, b.ppo.learning_rate, b.meta)


def test_where_the_meta_step_starts():
    """With no meta-training steps the meta policy is where the meta step starts: the policy that learnt the task
    (FTML), the slot's fresh initialisation, or the last meta policy, the latter two with the newest statistics."""
    family = envs.make("point_goal")
    no_meta = dataclasses.replace(SMALL_META, num_meta_steps=0, value_fit_steps=0)
    learn = {}

    def run(**fields):
        config = comps.CoMPSConfig(ppo=SMALL_PPO, meta=no_meta, max_tasks=3, num_skilled=3, num_offpolicy=5, **fields)
        method = methods.make("comps", family, config)
        key = tuple(sorted(fields.items()))
        learn[key] = jax.jit(method.learn_task)
        states = [method.init(jax.random.PRNGKey(0))]
        for i in range(2):
            states.append(learn[key](states[-1], envs.task_at(family, i))[0])
        return states

    def learnt_statistics(policy):
        assert float(policy["obs_norm"].count) > 0  # the RL step's statistics, not the identity normaliser

    warm = run()
    assert warm[0].fresh is None
    chex.assert_trees_all_equal(warm[1].params.policy, warm[1].meta.policy)
    fresh = run(warm_start=False)
    s0, s1, s2 = fresh
    chex.assert_shape(s0.fresh["log_std"], (3, family.action_size))
    for task, state in ((0, s1), (1, s2)):
        slot = jax.tree.map(lambda x: x[task], s0.fresh)
        chex.assert_trees_all_equal({k: v for k, v in state.meta.policy.items() if k != "obs_norm"},
                                    {k: v for k, v in slot.items() if k != "obs_norm"})
        learnt_statistics(state.meta.policy)
    w = np.asarray(s0.fresh["mean"][0]["w"])
    assert not np.allclose(w[0], w[1]) and not np.allclose(w[0], np.asarray(s0.params.policy["mean"][0]["w"]))
    # The fresh draws take nothing from the seed's other keys: the RL step of task 1 is the other rungs' own.
    chex.assert_trees_all_equal(s1.stores, warm[1].stores)
    last = run(warm_start=False, meta_start="last")
    assert last[0].fresh is None
    for state in last[1:]:
        chex.assert_trees_all_equal(state.meta.policy["mean"], last[0].meta.policy["mean"])
        learnt_statistics(state.meta.policy)
    # The warm start with the last meta policy's std: the learnt mean, the std the meta step last had (with no
    # meta-training steps, the initial one), where PPO has moved its own.
    std = run(warm_start_std="meta")
    chex.assert_trees_all_equal(std[1].meta.policy["mean"], warm[1].meta.policy["mean"])  # task 1: the same PPO
    assert not np.allclose(warm[1].meta.policy["log_std"], std[0].meta.policy["log_std"])
    for state in std[1:]:
        chex.assert_trees_all_equal(state.meta.policy["log_std"], std[0].meta.policy["log_std"])
        learnt_statistics(state.meta.policy)
    with pytest.raises(ValueError, match="warm_start_std"):
        comps.CoMPSConfig(warm_start_std="init")
    # Ignored with the warm start.
    config = comps.CoMPSConfig(ppo=SMALL_PPO, meta=no_meta, max_tasks=3, num_skilled=3, num_offpolicy=5,
                               meta_start="last")
    assert methods.make("comps", family, config).init(jax.random.PRNGKey(0)).fresh is None


def test_runs_made_before_meta_start_are_read_as_they_ran():
    for name, earlier in (("gmps_ppo", "last"), ("gmps_ppo_is", "last"), ("comps", "fresh")):
        stored = configs.to_json(methods.default_config(name, "point_goal"))
        assert methods.resolve_config(name, "point_goal", stored=stored).meta_start == stored["meta_start"]
        del stored["meta_start"]
        assert methods.resolve_config(name, "point_goal", stored=stored).meta_start == earlier
    assert methods.default_config("gmps_ppo", "point_goal").meta_start == "fresh"
    assert methods.default_config("gmps_ppo_last", "point_goal").meta_start == "last"


def test_gmps_ppo_is_registered_without_importance_weights():
    method = methods.make("gmps_ppo", envs.make("point_goal"))
    assert method.name == "gmps_ppo"
    assert not method.config.meta.importance_sampling and not method.config.meta.vtrace_baseline
    assert methods.make("comps", envs.make("point_goal")).config.meta.importance_sampling


def test_comps_in_the_continual_loop():
    family = envs.make("point_goal")
    config = comps.CoMPSConfig(ppo=SMALL_PPO, meta=SMALL_META, max_tasks=2, num_skilled=2, num_offpolicy=3)
    states, metrics = continual.run_seeds(methods.make("comps", family, config), envs.sequence(family, num_tasks=2),
                                          jax.random.split(jax.random.PRNGKey(0), 2))
    chex.assert_shape(metrics.iterations, (2, 2))  # [seeds, tasks]
    np.testing.assert_array_equal(states.stores.task_valid, True)  # both seeds learnt both tasks into their slots
    np.testing.assert_array_equal(states.task_index, [2, 2])
    # The seeds are independent draws: their policies differ.
    w = np.asarray(states.params.policy["mean"][0]["w"])
    assert not np.allclose(w[0], w[1])


def test_learning_past_max_tasks_is_refused():
    family = envs.make("point_goal")
    config = comps.CoMPSConfig(ppo=SMALL_PPO, meta=SMALL_META, max_tasks=2, num_skilled=2, num_offpolicy=3)
    method = methods.make("comps", family, config)
    with pytest.raises(ValueError, match="max_tasks=2"):
        continual.run_sequence(method, envs.sequence(family, num_tasks=3), jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="max_tasks=2"):
        continual.learn_at(method, method.init(jax.random.PRNGKey(0)), envs.sequence(family, num_tasks=3), 0)
    full = method.init(jax.random.PRNGKey(0))._replace(task_index=jax.numpy.int32(2))
    with pytest.raises(ValueError, match="past max_tasks=2"):
        method.learn_task(full, envs.task_at(family, 0))


def test_learnt_inner_step_sizes_live_in_the_policy_and_survive_every_meta_start():
    """Meta-SGD's step sizes (``MetaConfig.inner_step_sizes="learnt"``) are θ's: they start at α, every reading of
    where the meta step starts keeps the meta-learnt ones, and no gradient of PPO's loss reaches them."""
    family = envs.make("point_goal")
    learnt_meta = dataclasses.replace(SMALL_META, inner_step_sizes="learnt")
    for fields in ({}, {"warm_start_std": "meta"}, {"warm_start": False}, {"warm_start": False, "meta_start": "last"}):
        config = comps.CoMPSConfig(ppo=SMALL_PPO, meta=learnt_meta, max_tasks=2, num_skilled=3, num_offpolicy=5,
                                   **fields)
        state = methods.make("comps", family, config).init(jax.random.PRNGKey(0))
        for policy in (state.params.policy, state.meta.policy):
            for leaf in jax.tree.leaves(policy["inner_lr"]):
                np.testing.assert_array_equal(np.asarray(leaf), np.float32(learnt_meta.inner_learning_rate))
        learnt = {**state.params.policy, "inner_lr": jax.tree.map(lambda x: x * 3.0, state.params.policy["inner_lr"])}
        chex.assert_trees_all_equal(comps.meta_start(config, state, learnt)["inner_lr"], learnt["inner_lr"])
    params = networks.ActorCriticParams(state.params.policy, state.params.value)
    n = 8
    batch = {"obs": jnp.ones((n, family.obs_size)), "action": jnp.full((n, family.action_size), 0.3),
             "log_prob": jnp.full((n,), -1.0), "valid": jnp.ones((n,)), "advantage": jnp.linspace(-1.0, 1.0, n),
             "target": jnp.ones((n,))}
    grads = jax.grad(lambda p: ppo.ppo_loss(p, batch, SMALL_PPO)[0])(params)
    for leaf in jax.tree.leaves(grads.policy["inner_lr"]):
        np.testing.assert_array_equal(np.asarray(leaf), 0.0)
    assert float(jnp.max(jnp.abs(grads.policy["mean"][0]["w"]))) > 0
