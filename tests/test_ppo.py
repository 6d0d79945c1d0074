"""Tests of the RL step: GAE laws, the stopping rule, NaN handling, learning on Point Goal, config checks."""

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jcomps import envs
from jcomps.training import acting, networks, ppo

SMALL = ppo.PPOConfig(num_trajectories=4, num_updates=4, minibatch_size=64, hidden_sizes=(16,), budget=6)


def _discounted(rewards, bootstrap, discount):
    out = np.zeros_like(rewards)
    acc = bootstrap
    for t in reversed(range(len(rewards))):
        acc = rewards[t] + discount * acc
        out[t] = acc
    return out


def test_gae_lambda_one_gives_bootstrapped_discounted_return():
    rng = np.random.default_rng(0)
    rewards = rng.normal(size=(7, 3)).astype(np.float32)
    values = rng.normal(size=(7, 3)).astype(np.float32)
    boot = rng.normal(size=(3,)).astype(np.float32)
    _, targets = ppo.gae(rewards, values, boot, np.zeros_like(rewards), 0.9, 1.0)
    chex.assert_trees_all_close(np.asarray(targets), _discounted(rewards, boot, 0.9), rtol=1e-5, atol=1e-5)


def test_gae_lambda_zero_is_one_step_td():
    rng = np.random.default_rng(1)
    rewards, values = rng.normal(size=(2, 5, 2)).astype(np.float32)
    boot = rng.normal(size=(2,)).astype(np.float32)
    adv, _ = ppo.gae(rewards, values, boot, np.zeros_like(rewards), 0.9, 0.0)
    next_v = np.concatenate([values[1:], boot[None]])
    chex.assert_trees_all_close(np.asarray(adv), rewards + 0.9 * next_v - values, rtol=1e-5, atol=1e-5)


def test_gae_termination_cuts_bootstrap_but_truncation_does_not():
    rewards = np.ones((4, 2), np.float32)
    values = np.zeros((4, 2), np.float32)
    boot = np.full((2,), 10.0, np.float32)
    dones = np.zeros((4, 2), np.float32)
    dones[3, 1] = 1.0  # env 1 terminates at its last step; env 0 is truncated at T
    _, targets = ppo.gae(rewards, values, boot, dones, 0.5, 1.0)
    assert np.isclose(targets[3, 0], 1.0 + 0.5 * 10.0)
    assert np.isclose(targets[3, 1], 1.0)
    # A termination in the middle separates the episode before it from what follows.
    dones = np.zeros((4, 2), np.float32)
    dones[1, :] = 1.0
    _, targets = ppo.gae(rewards, values, boot, dones, 0.5, 1.0)
    chex.assert_trees_all_close(np.asarray(targets[:2, 0]), np.array([1.5, 1.0]), atol=1e-6)


def _run(family, config, seed=0):
    optimizer = ppo.make_optimizer(config)
    params = ppo.init_params(config, family, jax.random.PRNGKey(seed))
    task = envs.task_at(family, 0)
    return jax.jit(lambda p, o, r: ppo.rl_step(config, family, p, o, task, r))(
        params, optimizer.init(params), jax.random.PRNGKey(seed + 1)), params


@pytest.fixture(scope="module")
def point():
    return envs.make("point_goal")


def test_stops_at_threshold(point):
    easy = dataclasses.replace(point, success_threshold=0.0)
    out, params = _run(easy, SMALL)
    assert int(out.iterations) == 1 and bool(out.solved)
    np.testing.assert_array_equal(np.asarray(out.metrics.valid), [True] + [False] * 5)
    chex.assert_trees_all_equal(out.params, params)  # no update once the threshold is reached


def test_budget_spent_when_threshold_unreachable(point):
    hard = dataclasses.replace(point, success_threshold=2.0)
    out, params = _run(hard, SMALL)
    assert int(out.iterations) == SMALL.budget and not bool(out.solved)
    assert np.all(np.asarray(out.metrics.valid))
    assert np.all(np.asarray(out.metrics.nonfinite) == 0)
    assert not np.allclose(np.asarray(out.params.policy["log_std"]), np.asarray(params.policy["log_std"])) or \
        not np.allclose(np.asarray(out.params.value[0]["w"]), np.asarray(params.value[0]["w"]))


def test_nan_rewards_are_reported_and_not_trained_on(point):
    def nan_step(state, action, task):
        nxt = point.step_fn(state, action, task)
        return nxt._replace(reward=jnp.float32(jnp.nan))

    broken = dataclasses.replace(point, success_threshold=2.0, step_fn=nan_step)
    out, params = _run(broken, dataclasses.replace(SMALL, budget=2))
    assert np.all(np.asarray(out.metrics.nonfinite) == 1)
    chex.assert_trees_all_equal(out.params, params)


def test_ppo_raises_return_on_point_goal(point):
    never = dataclasses.replace(point, success_threshold=2.0)
    config = ppo.PPOConfig(budget=15)
    out, _ = _run(never, config)
    ret = np.asarray(out.metrics.mean_return)
    assert ret[-3:].mean() > ret[:3].mean() + 20.0, ret


@pytest.mark.parametrize("field,value", [
    ("num_trajectories", 0), ("learning_rate", -1.0), ("learning_rate", float("nan")), ("discount", 1.5),
    ("budget", 0), ("hidden_sizes", ()), ("clip_epsilon", 0.0), ("surrogate", "reinforce"), ("minibatch_size", -1),
])
def test_bad_config_names_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        ppo.PPOConfig(**{field: value})


def test_rollout_shapes_and_truncation_bootstrap_obs(point):
    policy = ppo.init_params(SMALL, point, jax.random.PRNGKey(0)).policy
    from jcomps.training import acting

    traj = jax.jit(lambda r: acting.rollout(point, policy, envs.task_at(point, 0), r, 3))(jax.random.PRNGKey(0))
    T = point.max_steps
    chex.assert_shape([traj.obs, traj.action], [(T, 3, 2), (T, 3, 2)])
    chex.assert_shape([traj.reward, traj.log_prob, traj.done, traj.valid, traj.success], (T, 3))
    chex.assert_shape(traj.last_obs, (3, 2))
    # The observation after the last step is the last obs plus the last (clipped) move.
    moved = traj.obs[-1] + 0.1 * jnp.clip(traj.action[-1], -1, 1)
    chex.assert_trees_all_close(traj.last_obs, moved, atol=1e-6)


# ------------------------------------------------------------------ observation normalisation and reward scale

@pytest.mark.parametrize("normalize", [True, False])
def test_rl_step_updates_the_statistics_only_when_normalising(point, normalize):
    hard = dataclasses.replace(point, success_threshold=2.0)
    out, params = _run(hard, dataclasses.replace(SMALL, budget=2, normalize_observations=normalize))
    norm = out.params.policy["obs_norm"]
    if normalize:  # two iterations of 4 episodes of T_max steps were merged
        assert float(norm.count) == 2 * 4 * point.max_steps
        assert float(jnp.min(norm.var)) > 0 and not np.allclose(np.asarray(norm.var), 1.0)
    else:
        chex.assert_trees_all_equal(norm, params.policy["obs_norm"])


def test_reward_scale_scales_value_targets():
    # GAE is linear: scaled rewards and values give scaled advantages and targets; the RL step feeds the value
    # loss the scaled targets (advantages are standardised per minibatch, so the policy sees no difference).
    rng = np.random.default_rng(2)
    rewards, values = rng.normal(size=(2, 6, 3)).astype(np.float32)
    boot = rng.normal(size=(3,)).astype(np.float32)
    dones = np.zeros_like(rewards)
    adv, targets = ppo.gae(0.1 * rewards, 0.1 * values, 0.1 * boot, dones, 0.99, 0.95)
    adv1, targets1 = ppo.gae(rewards, values, boot, dones, 0.99, 0.95)
    chex.assert_trees_all_close((adv, targets), (0.1 * adv1, 0.1 * targets1), rtol=1e-5, atol=1e-6)


def test_family_defaults_are_valid_configs():
    from jcomps import methods

    for family in envs.FAMILIES:
        config = methods.with_family_settings(ppo.PPOConfig(), family)
        for field, value in envs.settings(family, "ppo").items():
            assert getattr(config, field) == value
        for name in (m for m in methods.METHODS if m != "pearl"):  # every PPO-based method's RL step
            entry = methods.REGISTRY[name]
            every = entry.family_settings.get(methods.EVERY_FAMILY, {}).get("ppo", {})
            own = entry.family_settings.get(family, {}).get("ppo", {})
            expected = dataclasses.replace(config, **{**every, **own})
            assert methods.default_config(name, family).ppo == expected, name
    assert not methods.default_config("ppo_tl", "point_goal").ppo.normalize_observations


def test_method_ppo_starts_every_task_afresh(point):
    # ``ppo`` starts every task from its initial parameters (kept in the state), ``ppo_tl`` carries the parameters.
    from jcomps import methods

    config = methods.config_class("ppo")(ppo=dataclasses.replace(SMALL, budget=2))
    task = envs.task_at(point, 0)
    for name, carried in (("ppo", False), ("ppo_tl", True)):
        method = methods.make(name, point, config)
        state = method.init(jax.random.PRNGKey(0))
        trained, _ = jax.jit(method.learn_task)(state, task)
        again, _ = jax.jit(method.learn_task)(trained._replace(rng=state.rng), task)
        leaves = zip(jax.tree.leaves(again.params), jax.tree.leaves(trained.params))
        same = all(np.array_equal(a, b) for a, b in leaves)
        assert same != carried, name
        if not carried:
            chex.assert_trees_all_equal(trained.fresh, state.params)  # the start, unchanged by learning
            assert not all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(trained.params),
                                                                 jax.tree.leaves(state.params)))


def test_vanilla_surrogate_is_the_clipped_one_on_policy():
    # On the batch's own policy the ratio is 1, inside the clip range: both losses have the same gradient (one
    # full-batch vanilla step is what one PPO step would do). Off-policy they differ: vanilla ignores the ratio.
    params = networks.init_actor_critic(jax.random.PRNGKey(0), 3, 2, (8,), 0.5)
    rng = np.random.default_rng(3)
    obs = jnp.asarray(rng.normal(size=(40, 3)), jnp.float32)
    action = jnp.asarray(rng.normal(size=(40, 2)), jnp.float32)
    batch = {"obs": obs, "action": action, "log_prob": networks.GAUSSIAN.log_prob(params.policy, obs, action),
             "valid": jnp.ones((40,), jnp.float32), "advantage": jnp.asarray(rng.normal(size=40), jnp.float32),
             "target": jnp.zeros((40,), jnp.float32)}
    def grad(b, surrogate):
        return jax.grad(lambda p: ppo.ppo_loss(p, b, dataclasses.replace(SMALL, surrogate=surrogate))[0])(params)

    chex.assert_trees_all_close(grad(batch, "vanilla"), grad(batch, "clipped"), rtol=1e-5, atol=1e-7)
    stale = {**batch, "log_prob": batch["log_prob"] - 0.3}
    diff = jax.tree.map(lambda a, b: float(jnp.max(jnp.abs(a - b))), grad(stale, "vanilla"), grad(stale, "clipped"))
    assert max(jax.tree.leaves(diff)) > 1e-4


def test_fixed_budget_run_stops_once_solved_and_long_enough(point):
    """``run_at_least`` (the held-out meta-test): once the threshold was reached and that many iterations ran, the
    rest of the fixed budget is left unrun; what was run, and the iterations-to-success, equal the full run's."""
    easy = dataclasses.replace(point, success_threshold=0.0)
    optimizer = ppo.make_optimizer(SMALL)
    params = ppo.init_params(SMALL, easy, jax.random.PRNGKey(0))
    task = envs.task_at(easy, 0)

    def run(at_least):
        return jax.jit(lambda p, o, r: ppo.rl_step(SMALL, easy, p, o, task, r, stop_at_threshold=False,
                                                   run_at_least=at_least))(
            params, optimizer.init(params), jax.random.PRNGKey(1))

    full, short = run(None), run(3)
    np.testing.assert_array_equal(np.asarray(full.metrics.valid), [True] * SMALL.budget)
    np.testing.assert_array_equal(np.asarray(short.metrics.valid), [True] * 3 + [False] * (SMALL.budget - 3))
    chex.assert_trees_all_equal(jax.tree.map(lambda x: x[:3], full.metrics), jax.tree.map(lambda x: x[:3],
                                                                                         short.metrics))
    assert int(full.iterations) == int(short.iterations) == 1 and bool(full.solved) and bool(short.solved)


CRITIC = ppo.PPOConfig(num_trajectories=4, num_updates=8, minibatch_size=64, hidden_sizes=(16,), budget=20,
                       discount=0.5, learning_rate=1e-2)


def _critic_run(point, reward_of):
    """PPO (``CRITIC``, the whole budget) on Point Goal with the reward ``reward_of(next_state)``."""
    def step(state, action, task):
        nxt = point.step_fn(state, action, task)
        return nxt._replace(reward=jnp.asarray(reward_of(nxt), jnp.float32))

    out, _ = _run(dataclasses.replace(point, success_threshold=2.0, step_fn=step), CRITIC)
    return np.asarray(out.metrics.value_loss), np.asarray(out.metrics.value_ev)


def test_the_critic_fits_a_constant_reward(point):
    """A constant reward: the value targets are one constant (the truncation is bootstrapped), which the critic
    learns, its error going to 0 within the budget's updates."""
    loss, ev = _critic_run(point, lambda s: -1.0)
    assert loss[-5:].mean() < 0.02 * loss[0], loss
    assert np.all(np.isfinite(ev))  # measured at every iteration that updated (all of them here)


def test_the_critics_explained_variance_goes_to_one_on_returns_it_can_fit(point):
    """A reward that is the point's x coordinate: the returns are a smooth function of the state, and the critic's
    explained variance of them, measured on each batch before its update, rises from below 0 towards 1."""
    _, ev = _critic_run(point, lambda s: s.obs[0])
    assert ev[0] < 0.0 and ev[-5:].mean() > 0.9, ev


def test_the_reported_explained_variance_is_the_batchs_before_the_update(point):
    config = dataclasses.replace(SMALL, num_updates=2)
    params = ppo.init_params(config, point, jax.random.PRNGKey(3))
    traj = jax.jit(lambda p, k: acting.rollout(point, p.policy, envs.task_at(point, 0), k, config.num_trajectories))(
        params, jax.random.PRNGKey(4))
    optimizer = ppo.make_optimizer(config)
    new, _, terms, _ = ppo.ppo_update(config, optimizer, params, optimizer.init(params), traj, jax.random.PRNGKey(5))
    flat = ppo.flat_batch(config, params, traj)
    valid = np.asarray(flat["valid"]) > 0
    target, value = np.asarray(flat["target"])[valid], np.asarray(flat["value"])[valid]
    np.testing.assert_allclose(terms.value_ev, 1.0 - np.var(target - value) / np.var(target), rtol=1e-4)
    np.testing.assert_allclose(ppo.batch_value_ev({**flat, "value": flat["target"]}), 1.0)
    assert not np.allclose(ppo.batch_value_ev(ppo.flat_batch(config, new, traj)), terms.value_ev)  # it moved
