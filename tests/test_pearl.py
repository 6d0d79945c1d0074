"""PEARL: laws of its parts (SAC target, product of Gaussians, KL, Polyak, per-slot buffers) and the method through
the runner (CLI, chunks, exact resume)."""

import dataclasses
import json
import os

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jcomps import acting, buffers, continual, envs, experiment, methods
from jcomps.methods import pearl

TINY = pearl.PEARLConfig(num_trajectories=2, budget=1, num_updates=1, minibatch_size=8, meta_batch=2, tau=0.05,
                         context_size=4, hidden_sizes=(8, 8), encoder_hidden_sizes=(8,), max_tasks=3,
                         buffer_size=1000)


@pytest.fixture(scope="module")
def family():
    return envs.make("point_goal")


@pytest.fixture(scope="module")
def tiny(family):
    """The tiny PEARL, its jitted learn_task (shared by the tests), and the states after tasks 1 and 2."""
    method = methods.make("pearl", family, TINY)
    learn = jax.jit(chex.assert_max_traces(method.learn_task, n=1))
    s0 = method.init(jax.random.PRNGKey(0))
    s1, m1 = learn(s0, envs.task_at(family, 0))
    s2, m2 = learn(s1, envs.task_at(family, 1))
    return method, s0, (s1, m1), (s2, m2)


def test_sac_target_equals_a_hand_computation(family):
    """brax's critic loss as PEARL feeds it (reward scale, discount, done, the mask as brax's truncation, z in the
    observation) equals 0.5·mean over rows and critics of (Q_k(s, a) − y)², y = c·r + γ(1 − d)(min_k Q̄_k(s', a') −
    α log π(a'|s')), a' ~ π(·|s') with the same key."""
    cfg = dataclasses.replace(TINY, reward_scale=5.0, discount=0.9)
    nets = pearl.make_networks(cfg, family)
    _, critic_loss, _ = pearl.sac_losses.make_losses(nets.sac, cfg.reward_scale, cfg.discount, family.action_size)
    k = jax.random.split(jax.random.PRNGKey(1), 8)
    n, width = 5, family.obs_size + cfg.latent_size
    obs, next_obs = jax.random.normal(k[0], (n, width)), jax.random.normal(k[1], (n, width))
    action = jnp.tanh(jax.random.normal(k[2], (n, family.action_size)))
    reward = jax.random.normal(k[3], (n,))
    done = jnp.array([0.0, 1.0, 0.0, 0.0, 0.0])
    mask = jnp.array([1.0, 1.0, 1.0, 0.0, 1.0])
    q, target_q = nets.sac.q_network.init(k[4]), nets.sac.q_network.init(k[5])
    policy_net = nets.sac.policy_network.init(k[6])
    alpha = 0.7
    loss = critic_loss(q, policy_net, None, target_q, alpha, pearl._transitions(obs, action, reward, done, next_obs,
                                                                               mask), k[7])
    # by hand: a' = tanh(loc + scale·ε), ε ~ N(0, 1) from the same key, and its tanh-corrected log-probability
    act = pearl.make_act(nets)
    noise = jax.random.normal(k[7], (n, family.action_size))
    next_action, next_log_prob = act({"net": policy_net, "z": jnp.zeros((0,))}, next_obs, noise)
    q_next = jnp.min(nets.sac.q_network.apply(None, target_q, next_obs, next_action), axis=-1)
    y = cfg.reward_scale * reward + cfg.discount * (1.0 - done) * (q_next - alpha * next_log_prob)
    q_now = nets.sac.q_network.apply(None, q, obs, action)
    expected = 0.5 * jnp.mean(jnp.square((q_now - y[:, None]) * mask[:, None]))
    np.testing.assert_allclose(float(loss), float(expected), rtol=1e-5)
    # the tanh correction: log π(a) = log N(pre) − Σ log(1 − tanh(pre)²)
    params = nets.sac.policy_network.apply(None, policy_net, next_obs)
    loc, raw = jnp.split(params, 2, axis=-1)
    scale = jax.nn.softplus(raw) + 0.001
    pre = loc + scale * noise
    gauss = jnp.sum(-0.5 * jnp.square(noise) - jnp.log(scale) - 0.5 * jnp.log(2 * jnp.pi), axis=-1)
    np.testing.assert_allclose(next_log_prob, gauss - jnp.sum(jnp.log(1 - jnp.square(jnp.tanh(pre))), axis=-1),
                               rtol=1e-3, atol=1e-3)


def test_posterior_is_the_normalised_product_of_gaussians():
    mu = jnp.array([[1.0, 0.0], [3.0, 2.0], [100.0, 100.0]])
    var = jnp.array([[1.0, 2.0], [1.0, 2.0], [0.5, 0.5]])
    post_mu, post_var = pearl.product_of_gaussians(mu, var, jnp.array([1.0, 1.0, 0.0]))  # row 3 left out
    # closed form: N(1, 1)·N(3, 1) ∝ N(2, 1/2); N(0, 2)·N(2, 2) ∝ N(1, 1)
    np.testing.assert_allclose(post_mu, [2.0, 1.0], rtol=1e-6)
    np.testing.assert_allclose(post_var, [0.5, 1.0], rtol=1e-6)
    # permutation-invariant, and the prior N(0, I) with no row
    perm = jnp.array([2, 0, 1])
    np.testing.assert_allclose(pearl.product_of_gaussians(mu[perm], var[perm], jnp.array([0.0, 1.0, 1.0]))[0],
                               post_mu, rtol=1e-6)
    empty = pearl.product_of_gaussians(mu, var, jnp.zeros(3))
    np.testing.assert_array_equal(empty[0], [0.0, 0.0])
    np.testing.assert_array_equal(empty[1], [1.0, 1.0])


def test_kl_to_the_prior_is_zero_at_the_prior_and_the_closed_form_elsewhere():
    assert float(pearl.kl_to_prior(jnp.zeros(5), jnp.ones(5))) == 0.0
    mu, var = jnp.array([0.5, -1.0]), jnp.array([0.25, 2.0])
    expected = sum(0.5 * (v + m * m - 1 - np.log(v)) for m, v in zip([0.5, -1.0], [0.25, 2.0]))
    np.testing.assert_allclose(float(pearl.kl_to_prior(mu, var)), expected, rtol=1e-6)
    assert float(pearl.kl_to_prior(mu, var)) > 0


def test_a_gradient_step_moves_the_targets_by_exactly_tau(tiny):
    """One iteration with one gradient step: target' = (1 − τ)·target + τ·Q', and the target starts as Q."""
    _, s0, (s1, m1), _ = tiny
    chex.assert_trees_all_equal(s0.target_q, s0.q)
    assert not bool(m1.solved)  # the iteration made its update
    moved = jax.tree.map(lambda t, q: (1 - TINY.tau) * t + TINY.tau * q, s0.target_q, s1.q)
    chex.assert_trees_all_close(s1.target_q, moved, rtol=1e-6, atol=1e-8)
    assert not jax.tree.all(jax.tree.map(lambda a, b: bool(jnp.all(a == b)), s1.q, s0.q))


def test_buffers_keep_every_task_and_never_mix_slots(tiny, family):
    method, s0, (s1, m1), (s2, m2) = tiny
    batch = TINY.num_trajectories * family.max_steps
    np.testing.assert_array_equal(s1.replay.count, [int(m1.iterations) * batch, 0, 0])
    np.testing.assert_array_equal(s2.replay.count, [int(m1.iterations) * batch, int(m2.iterations) * batch, 0])
    chex.assert_trees_all_equal(jax.tree.map(lambda x: x[0], s2.replay), jax.tree.map(lambda x: x[0], s1.replay))
    # unit laws: a write to slot 1 leaves slot 0 as it was; a sample of a slot holds only that slot's rows; the
    # ring overwrites the oldest batch
    store = buffers.transitions_init(2, 2 * batch, family.obs_size, family.action_size)
    policy = s0.params.policy
    traj = acting.rollout(family, policy, envs.task_at(family, 0), jax.random.PRNGKey(3), TINY.num_trajectories,
                          act=method.act)
    ones = traj._replace(obs=jnp.ones_like(traj.obs), last_obs=jnp.ones_like(traj.last_obs))
    store = buffers.transitions_add(store, 0, traj)
    before = jax.tree.map(lambda x: x[0], store)
    for _ in range(3):
        store = buffers.transitions_add(store, 1, ones)
    chex.assert_trees_all_equal(jax.tree.map(lambda x: x[0], store), before)
    rows, mask = buffers.transitions_sample(store, 1, 64, jax.random.PRNGKey(4))
    np.testing.assert_array_equal(rows["obs"], 1.0)
    assert float(mask.min()) == 1.0 and int(store.count[1]) == 3 * batch
    rows, mask = buffers.transitions_sample(buffers.transitions_init(2, batch, 2, 2), 0, 4, jax.random.PRNGKey(5))
    np.testing.assert_array_equal(mask, 0.0)  # an empty slot gives no valid row
    # the next observation of the last step is the one reached at T_max (a truncation, not a termination)
    flat = buffers.transitions_of(traj)
    np.testing.assert_array_equal(flat["next_obs"].reshape(traj.obs.shape)[-1], traj.last_obs)
    np.testing.assert_array_equal(flat["done"], 0.0)


def test_pearl_learn_task_reports_the_shared_metrics(tiny, family):
    method, s0, (s1, m1), _ = tiny
    assert m1.per_iteration.valid.shape == (TINY.budget,)
    assert 1 <= int(m1.iterations) <= TINY.budget and int(s1.task_index) == 1
    chex.assert_trees_all_equal_shapes_and_dtypes(s1, s0)  # a lax.scan over tasks can carry it
    assert methods.base.env_steps_per_iteration(method) == TINY.num_trajectories * family.max_steps
    policy = methods.base.policy_for(method, s1, jnp.int32(0), jax.random.PRNGKey(0))
    assert policy["z"].shape == (TINY.latent_size,)
    held = continual.heldout_adaptation(method, continual.EvalConfig(heldout_iterations=1, heldout_budget=3), s1,
                                        envs.held_out(family), jax.random.PRNGKey(1))
    assert held.success_rate.shape[1] == 2 and held.iterations.shape == held.solved.shape


@pytest.mark.parametrize("field,value", [("kl_weight", -1.0), ("tau", 0.0), ("latent_size", 0), ("alpha", 0.0),
                                         ("meta_batch", 0), ("hidden_sizes", ())])
def test_bad_pearl_config_names_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        pearl.PEARLConfig(**{field: value})


def test_pearl_ignores_the_family_ppo_settings():
    assert methods.default_config("pearl", "cheetah_vel") == pearl.PEARLConfig()


# --- through the runner: CLI, chunks, checkpoints, exact resume ---

TINY_RUN = ["--methods", "pearl", "--num-tasks", "3", "--seeds", "2", "--chunk-tasks", "1", "--budget", "2",
            "--num-trajectories", "2", "--hidden-sizes", "8", "8", "--num-updates", "2", "--minibatch-size", "8",
            "--set", "pearl.encoder_hidden_sizes=8", "--set", "pearl.context_size=4", "--set", "pearl.max_tasks=3",
            "--set", "pearl.buffer_size=1000", "--heldout-iterations", "1", "--heldout-budget", "2",
            "--backward-tasks", "1"]


@pytest.fixture(scope="module")
def pearl_run(runner, tmp_path_factory):
    out = tmp_path_factory.mktemp("pearl") / "full"
    runner.main(TINY_RUN + ["--out", str(out)])
    return out


def test_pearl_runs_end_to_end_from_the_cli(pearl_run):
    results = json.loads((pearl_run / "results.json").read_text())
    m = results["methods"]["pearl"]
    assert np.asarray(m["iterations_to_success"]).shape == (2, 3)
    assert m["env_steps_per_iteration"] == 2 * 100
    assert m["nonfinite_iterations"] == 0
    run = json.loads((pearl_run / "run.json").read_text())
    assert run["methods"]["pearl"]["context_size"] == 4 and run["methods"]["pearl"]["hidden_sizes"] == [8, 8]


def test_killed_and_resumed_pearl_equals_the_uninterrupted_run(runner, pearl_run, tmp_path):
    out = tmp_path / "killed"
    args = runner.parse_args(TINY_RUN + ["--out", str(out)])
    experiment.open_run_dir(str(out), experiment.describe(args.run, args.eval, args.configs), resume=False)
    assert experiment.run_method(str(out), "pearl", args.run, args.eval, args.configs["pearl"], resume=False,
                                 programs=runner.PROGRAMS, stop_after_chunks=1) is None
    assert sorted(os.listdir(out / "checkpoints" / "pearl")) == ["1"]
    runner.main(["--out", str(out), "--resume"])
    with np.load(pearl_run / "raw" / "pearl.npz") as fa, np.load(out / "raw" / "pearl.npz") as fb:
        assert fa.files == fb.files
        for key in fa.files:
            if key != "seconds":
                np.testing.assert_array_equal(fa[key], fb[key], err_msg=key)


def test_render_replays_pearl_with_each_task_latent(render, pearl_run, tmp_path):
    lines = []
    paths = render.render(str(pearl_run), tasks=[1, 3], out_dir=str(tmp_path), print_fn=lines.append)
    assert [os.path.basename(p) for p in paths] == ["pearl_seed0_task01.png", "pearl_seed0_task03.png"]
    assert all(os.path.getsize(p) > 1000 for p in paths) and "success rate" in lines[0]
