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

from jcomps import continual, envs, methods
from jcomps.methods import pearl
from jcomps.training import acting, buffers

TINY = pearl.PEARLConfig(num_trajectories=2, budget=1, num_updates=1, minibatch_size=8, meta_batch=2, tau=0.05,
                         context_size=4, hidden_sizes=(8, 8), encoder_hidden_sizes=(8,), max_tasks=3,
                         buffer_size=1000, initial_steps=100)


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
    loss = jax.jit(lambda t: critic_loss(q, policy_net, None, target_q, alpha, t, k[7]))(
        pearl._transitions(obs, action, reward, done, next_obs, mask))
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
    first = TINY.initial_episodes(family) * family.max_steps  # the prior-z collection before the first iteration
    assert first == 100 and method.env_steps_before_task == first
    np.testing.assert_array_equal(s1.replay.count, [first + int(m1.iterations) * batch, 0, 0])
    np.testing.assert_array_equal(s2.replay.count, [first + int(m1.iterations) * batch,
                                                    first + int(m2.iterations) * batch, 0])
    chex.assert_trees_all_equal(jax.tree.map(lambda x: x[0], s2.replay), jax.tree.map(lambda x: x[0], s1.replay))
    # unit laws: a write to slot 1 leaves slot 0 as it was; a sample holds only rows written to that slot; the
    # ring overwrites its oldest batch
    store = buffers.transitions_init(2, 2 * batch, family.obs_size, family.action_size)
    traj = acting.rollout(family, s0.params.policy, envs.task_at(family, 0), jax.random.PRNGKey(3),
                          TINY.num_trajectories, actor=method.actor)
    marked = lambda v: traj._replace(obs=jnp.full_like(traj.obs, v), last_obs=jnp.full_like(traj.last_obs, v))  # noqa
    store = buffers.transitions_add(store, 0, traj)
    before = jax.tree.map(lambda x: x[0], store)
    store = buffers.transitions_add(store, 1, marked(1.0))
    rows, mask = buffers.transitions_sample(store, 1, 256, jax.random.PRNGKey(4))
    np.testing.assert_array_equal(rows["obs"], 1.0)  # only the held half of the ring is sampled
    assert float(mask.min()) == 1.0
    store = buffers.transitions_add(buffers.transitions_add(store, 1, marked(2.0)), 1, marked(3.0))
    chex.assert_trees_all_equal(jax.tree.map(lambda x: x[0], store), before)
    np.testing.assert_array_equal(store.obs[1, :batch], 3.0)  # batch 3 replaced batch 1, the oldest
    np.testing.assert_array_equal(store.obs[1, batch:], 2.0)
    assert int(store.count[1]) == 3 * batch
    rows, mask = buffers.transitions_sample(buffers.transitions_init(2, batch, 2, 2), 0, 4, jax.random.PRNGKey(5))
    np.testing.assert_array_equal(mask, 0.0)  # an empty slot gives no valid row
    # a ring that is not a multiple of the batch wraps around; a cleared slot is sampled from its new rows only
    half = batch // 2
    ring = buffers.transitions_init(1, 3 * half, family.obs_size, family.action_size)
    ring = buffers.transitions_add(buffers.transitions_add(ring, 0, marked(1.0)), 0, marked(2.0))
    np.testing.assert_array_equal(ring.obs[0, :half], 2.0)
    np.testing.assert_array_equal(ring.obs[0, half:batch], 1.0)
    np.testing.assert_array_equal(ring.obs[0, batch:], 2.0)
    small = buffers.transitions_init(1, half, family.obs_size, family.action_size)  # a batch larger than the ring
    np.testing.assert_array_equal(buffers.transitions_add(small, 0, traj).obs[0],
                                  buffers.transitions_of(traj)["obs"][batch - half:])
    cleared = buffers.transitions_add(buffers.transitions_clear(ring, 0), 0, marked(3.0))
    rows, mask = buffers.transitions_sample(cleared, 0, 256, jax.random.PRNGKey(6))
    np.testing.assert_array_equal(rows["obs"], 3.0)
    assert int(cleared.count[0]) == batch
    # on families whose episodes end early, valid_only draws only transitions (never a row after an episode's end)
    ended = traj._replace(valid=traj.valid.at[traj.valid.shape[0] // 2:].set(0.0))
    store = buffers.transitions_add(buffers.transitions_init(1, batch, family.obs_size, family.action_size), 0, ended)
    rows, mask = buffers.transitions_sample(store, 0, 512, jax.random.PRNGKey(7), valid_only=True)
    assert float(mask.min()) == 1.0
    _, mask_any = buffers.transitions_sample(store, 0, 512, jax.random.PRNGKey(7))
    assert 0.3 < float(mask_any.mean()) < 0.7  # the uniform index meets the rows after the end half the time
    _, none = buffers.transitions_sample(buffers.transitions_init(1, batch, 2, 2), 0, 4, jax.random.PRNGKey(8), True)
    np.testing.assert_array_equal(none, 0.0)
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
    policy = methods.base.policy_for(method, s1, jnp.int32(0), None, jax.random.PRNGKey(0))
    assert policy["z"].shape == (TINY.latent_size,)
    held = continual.heldout_adaptation(method, continual.EvalConfig(heldout_iterations=1, heldout_budget=3), s1,
                                        envs.held_out(family), jax.random.PRNGKey(1))
    assert held.success_rate.shape[1] == 2 and held.iterations.shape == held.solved.shape


def test_the_encoder_learns_through_the_critic_loss(family):
    """The critics' and encoder's gradient equals that of oyster's critic loss written by hand, Σ_k mean (Q_k(s, a, z)
    − y)² with y under stop_gradient and z = μ + σ·ε from the posterior of each slot's context (KL weight 0)."""
    cfg = dataclasses.replace(TINY, kl_weight=0.0)
    nets = pearl.make_networks(cfg, family)
    _, critic_loss, _ = pearl.sac_losses.make_losses(nets.sac, cfg.reward_scale, cfg.discount, family.action_size)
    k = jax.random.split(jax.random.PRNGKey(7), 10)
    M, n, c, A = 2, 6, 4, family.action_size
    rows = {"obs": jax.random.normal(k[0], (M, n, family.obs_size)), "reward": jax.random.normal(k[2], (M, n)),
            "action": jnp.tanh(jax.random.normal(k[1], (M, n, A))), "done": jnp.zeros((M, n)),
            "next_obs": jax.random.normal(k[3], (M, n, family.obs_size))}
    contexts = jax.random.normal(k[4], (M, c, nets.context_size))
    ones = jnp.ones((M, n)), jnp.ones((M, c))
    q, target_q = nets.sac.q_network.init(k[5]), nets.sac.q_network.init(k[6])
    policy_net = nets.sac.policy_network.init(k[7])
    encoder = nets.encoder.init(k[8], jnp.zeros((1, nets.context_size)))
    alpha = 0.5
    (_, (q_loss, _, z)), (g_q, g_enc) = jax.jit(lambda qe: pearl.critic_grad(  # jitted: eager flax is slow
        cfg, nets, critic_loss, qe, policy_net, target_q, alpha, rows, ones[0], contexts, ones[1], k[9]))((q, encoder))
    act = pearl.make_act(nets)

    def by_hand(q, encoder):
        k_z, k_loss = jax.random.split(k[9])
        mu, var = jax.vmap(lambda x, m: pearl.posterior(cfg, nets, encoder, x, m))(contexts, ones[1])
        zs = jnp.broadcast_to((mu + jnp.sqrt(var) * jax.random.normal(k_z, mu.shape))[:, None], (M, n, mu.shape[-1]))
        s = jnp.concatenate([rows["obs"], zs], -1).reshape(M * n, -1)
        s2 = jnp.concatenate([rows["next_obs"], zs], -1).reshape(M * n, -1)
        a2, log_p2 = act({"net": policy_net, "z": jnp.zeros((0,))}, s2, jax.random.normal(k_loss, (M * n, A)))
        next_v = jnp.min(nets.sac.q_network.apply(None, target_q, s2, a2), -1) - alpha * log_p2
        y = jax.lax.stop_gradient(cfg.reward_scale * rows["reward"].reshape(-1) + cfg.discount * next_v)
        q_sa = nets.sac.q_network.apply(None, q, s, rows["action"].reshape(M * n, A))
        return jnp.sum(jnp.mean(jnp.square(q_sa - y[:, None]), axis=0))

    np.testing.assert_allclose(float(q_loss), float(jax.jit(by_hand)(q, encoder)), rtol=1e-5)
    hand_q, hand_enc = jax.jit(jax.grad(by_hand, argnums=(0, 1)))(q, encoder)
    chex.assert_trees_all_close((g_q, g_enc), (hand_q, hand_enc), rtol=1e-4, atol=1e-6)
    assert max(float(jnp.max(jnp.abs(g))) for g in jax.tree.leaves(g_enc)) > 0  # the encoder does learn


def test_policy_for_reads_each_slot_context(family, tiny):
    """The z of slot j's policy is a draw of the posterior of a context of slot j's data (by hand: the context drawn
    with the key's first half, q(z | c) by the encoder's product of Gaussians, the draw with its second half), and
    the task the caller names does not enter it."""
    method, _, _, (s2, _) = tiny
    p = pearl.setup(family, TINY)
    key = jax.random.PRNGKey(11)
    k_ctx, k_z = jax.random.split(key)
    store = pearl.context_store(p, s2)
    by_hand = []
    for slot in (0, 1):
        context, mask = pearl.sample_context(TINY, store, jnp.int32(slot), k_ctx, p.valid_only)
        assert float(jnp.sum(mask)) > 0  # the slot holds data: its posterior is not the prior
        mu, var = pearl.posterior(TINY, p.nets, s2.encoder, context, mask)
        by_hand.append(mu + jnp.sqrt(var) * jax.random.normal(k_z, mu.shape, jnp.float32))
    for slot in (0, 1):
        z = methods.base.policy_for(method, s2, jnp.int32(slot), None, key)["z"]
        np.testing.assert_allclose(z, by_hand[slot], rtol=1e-5, atol=1e-6)
        z_task = methods.base.policy_for(method, s2, jnp.int32(slot), envs.task_at(family, 1 - slot), key)["z"]
        np.testing.assert_array_equal(z_task, z)
    assert not np.allclose(by_hand[0], by_hand[1])  # the two slots' data give two posteriors


def test_auto_alpha_follows_the_entropy_and_contexts_without_next_obs(family):
    """With ``auto_alpha``, one Adam step moves log α by the learning rate, down while the policy's entropy is above
    the target −A/2 (brax's), up below it; ``context_next_obs=False`` encodes (s, a, r) only."""
    cfg = dataclasses.replace(TINY, auto_alpha=True, context_next_obs=False, learning_rate=1e-2)
    method = methods.make("pearl", family, cfg)
    assert pearl.make_networks(cfg, family).context_size == family.obs_size + family.action_size + 1
    s0 = method.init(jax.random.PRNGKey(4))
    s1, metrics = jax.jit(method.learn_task)(s0, envs.task_at(family, 0))
    entropy = float(metrics.per_iteration.entropy[0])
    step = float(s1.log_alpha - s0.log_alpha)
    assert step == pytest.approx(-cfg.learning_rate * np.sign(entropy + 0.5 * family.action_size), rel=1e-3)


@pytest.mark.parametrize("field,value", [("kl_weight", -1.0), ("tau", 0.0), ("latent_size", 0), ("alpha", 0.0),
                                         ("meta_batch", 0), ("hidden_sizes", ()), ("policy_reg", -1.0),
                                         ("current_slots", -1), ("current_slots", 5), ("num_updates", 0),
                                         ("updates_per_step", 0.0), ("initial_steps", -1),
                                         ("context_source", "posterior"), ("prior_fraction", 1.0),
                                         ("prior_fraction", 0.01)])
def test_bad_pearl_config_names_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        pearl.PEARLConfig(**{field: value})


def test_gradient_steps_draw_seen_slots_uniformly_or_keep_the_current_task():
    count = jnp.zeros((8,), jnp.int32).at[jnp.array([0, 2, 5])].set(100)
    keys = jax.random.split(jax.random.PRNGKey(0), 2000)
    uniform = np.asarray(jax.vmap(lambda k: pearl.draw_slots(pearl.PEARLConfig(max_tasks=8), count, 5, k))(keys))
    assert set(np.unique(uniform)) == {0, 2, 5}  # only slots that hold data, each about a third of the draws
    np.testing.assert_allclose(np.bincount(uniform.ravel(), minlength=8)[[0, 2, 5]] / uniform.size, 1 / 3, atol=0.02)
    cfg = pearl.PEARLConfig(max_tasks=8, current_slots=1)
    fixed = np.asarray(jax.vmap(lambda k: pearl.draw_slots(cfg, count, 5, k))(keys))
    assert (fixed[:, 0] == 5).all()  # the task being learnt, in every step
    np.testing.assert_array_equal(fixed[:, 1:], uniform[:, 1:])  # the rest drawn as before
    everything = pearl.PEARLConfig(max_tasks=8, current_slots=4)
    assert (np.asarray(pearl.draw_slots(everything, count, 2, keys[0])) == 2).all()


def test_pearl_takes_oysters_family_settings_not_the_family_ppo_settings():
    assert methods.default_config("pearl", "cheetah_vel") == pearl.PEARLConfig(
        context_size=100, updates_per_step=0.4, prior_fraction=0.4)
    assert methods.default_config("pearl", "metaworld") == pearl.PEARLConfig()
    ant_goal = methods.default_config("pearl", "ant_goal")
    assert (ant_goal.kl_weight, ant_goal.context_size) == (10.0, 256)  # kl_lambda 1.0 × its meta_batch 10


def test_oysters_ratio_of_gradient_steps_to_env_steps(family):
    """The default gradient steps per iteration are ``updates_per_step`` × the env steps collected (oyster's 0.5:
    1,000 per Point Goal iteration of 20 × 100 steps); an explicit ``num_updates`` wins."""
    config = methods.default_config("pearl", family)
    assert config.num_updates is None and config.updates_for(family) == 1000
    assert dataclasses.replace(config, num_updates=64).updates_for(family) == 64
    assert config.initial_episodes(family) == 2 and config.prior_episodes == 10  # oyster's 200 steps; 200 of 400


def test_the_encoder_buffer_holds_the_last_iterations_prior_episodes(tiny, family):
    """oyster's reading: each iteration empties slot i's encoder buffer and fills it with its prior-z episodes,
    which also go to the replay (before the posterior episodes); contexts, backward transfer and the next
    iteration's posterior read it alone."""
    method, s0, (s1, m1), _ = tiny
    prior_rows = TINY.prior_episodes * family.max_steps
    first = TINY.initial_episodes(family) * family.max_steps
    assert int(m1.iterations) == 1 and int(s1.contexts.count[0]) == prior_rows
    for key in ("obs", "action", "reward"):  # the iteration's prior episodes, as the replay holds them
        np.testing.assert_array_equal(getattr(s1.contexts, key)[0, :prior_rows],
                                      getattr(s1.replay, key)[0, first:first + prior_rows])
    again, _ = jax.jit(method.learn_task)(s1._replace(task_index=jnp.int32(0)), envs.task_at(family, 0))
    assert int(again.contexts.count[0]) == prior_rows  # emptied, then refilled: never accumulated
    assert not np.array_equal(again.contexts.obs[0, :prior_rows], s1.contexts.obs[0, :prior_rows])
    replay_reading = methods.make("pearl", family, dataclasses.replace(TINY, context_source="replay"))
    assert replay_reading.init(jax.random.PRNGKey(0)).contexts.obs.shape[1] == 0  # no encoder buffer


def test_the_kl_weighs_per_task_whatever_the_meta_batch(family):
    """``kl_weight`` multiplies the mean KL over a step's slots (oyster's kl_lambda × its meta-batch, per task), so
    the same context in 1 or 3 slots gives the same loss (a sum over slots would triple it)."""
    cfg = dataclasses.replace(TINY, kl_weight=2.0)
    nets = pearl.make_networks(cfg, family)
    _, critic_loss, _ = pearl.sac_losses.make_losses(nets.sac, cfg.reward_scale, cfg.discount, family.action_size)
    k = jax.random.split(jax.random.PRNGKey(3), 6)
    q, policy_net = nets.sac.q_network.init(k[0]), nets.sac.policy_network.init(k[1])
    encoder = nets.encoder.init(k[2], jnp.zeros((1, nets.context_size)))
    context = jax.random.normal(k[3], (1, 4, nets.context_size))

    def loss(M):
        rows = {"obs": jnp.zeros((M, 2, family.obs_size)), "action": jnp.zeros((M, 2, family.action_size)),
                "reward": jnp.zeros((M, 2)), "done": jnp.zeros((M, 2)), "next_obs": jnp.zeros((M, 2, family.obs_size))}
        total, (q_loss, kl, _) = pearl.critic_objective(cfg, nets, critic_loss, (q, encoder), policy_net, q, 1.0, rows,
                                                        jnp.zeros((M, 2)), jnp.repeat(context, M, 0),
                                                        jnp.ones((M, 4)), k[4])
        return float(total), float(q_loss), float(kl)

    (one, q1, kl1), (three, q3, _kl3) = loss(1), loss(3)
    assert q1 == q3 == 0.0 and kl1 > 0  # no valid row: the KL term alone
    assert one == pytest.approx(2.0 * kl1, rel=1e-6) and three == pytest.approx(one, rel=1e-6)


# --- through the runner: CLI, chunks, checkpoints, exact resume ---

TINY_RUN = ["--methods", "pearl", "--num-tasks", "3", "--seeds", "2", "--chunk-tasks", "1", "--budget", "2",
            "--num-trajectories", "2", "--hidden-sizes", "8", "8", "--num-updates", "2", "--minibatch-size", "8",
            "--set", "pearl.encoder_hidden_sizes=8", "--set", "pearl.context_size=4", "--set", "pearl.max_tasks=3",
            "--set", "pearl.buffer_size=1000", "--set", "pearl.initial_steps=100", "--heldout-iterations", "1",
            "--heldout-budget", "2",
            "--backward-tasks", "1"]


@pytest.fixture(scope="module")
def pearl_run(tiny_run):
    return tiny_run(TINY_RUN, "pearl")


def test_pearl_runs_end_to_end_from_the_cli(pearl_run):
    results = json.loads((pearl_run / "results.json").read_text())
    m = results["methods"]["pearl"]
    assert np.asarray(m["iterations_to_success"]).shape == (2, 3)
    assert m["env_steps_per_iteration"] == 2 * 100
    assert m["nonfinite_iterations"] == 0
    run = json.loads((pearl_run / "run.json").read_text())
    assert run["methods"]["pearl"]["context_size"] == 4 and run["methods"]["pearl"]["hidden_sizes"] == [8, 8]


def test_killed_and_resumed_pearl_equals_the_uninterrupted_run(runner, pearl_run, tmp_path, kill_and_resume):
    kill_and_resume(runner, TINY_RUN, tmp_path / "killed", ["pearl"], pearl_run)


def test_render_replays_pearl_with_each_task_latent(render, pearl_run, tmp_path):
    lines = []
    paths = render.render(str(pearl_run), tasks=[1, 3], out_dir=str(tmp_path), print_fn=lines.append)
    assert [os.path.basename(p) for p in paths] == ["pearl_seed0_task01.png", "pearl_seed0_task03.png"]
    assert all(os.path.getsize(p) > 1000 for p in paths) and "success rate" in lines[0]
