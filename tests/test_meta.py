"""Tests of the meta step: the meta-gradient against finite differences, second vs first order, masked slots,
and that meta training lowers the outer behaviour-cloning loss."""

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from jcomps import progress
from jcomps.numerics import masked_mean
from jcomps.training import buffers, meta, networks
from jcomps.training.acting import Trajectory

T, OBS, ACT, SLOTS, SKILLED, OFF = 4, 2, 1, 3, 3, 4
CONFIG = meta.MetaConfig(inner_trajectories=3, skilled_trajectories=2, inner_learning_rate=0.5, num_meta_steps=20,
                         num_outer_steps=1, outer_learning_rate=0.01)


def _stores(seed, dtype=np.float32):
    rng = np.random.default_rng(seed)
    f = lambda *s: rng.normal(size=s).astype(dtype)  # noqa: E731
    traj = Trajectory(f(SLOTS, T, OFF, OBS), f(SLOTS, T, OFF, ACT), f(SLOTS, T, OFF) - 1.0, f(SLOTS, T, OFF),
                      np.zeros((SLOTS, T, OFF), dtype), np.ones((SLOTS, T, OFF), dtype),
                      np.zeros((SLOTS, T, OFF), dtype), f(SLOTS, OFF, OBS))
    skilled = buffers.SkilledStore(f(SLOTS, T, SKILLED, OBS), 0.3 + 0.1 * f(SLOTS, T, SKILLED, ACT),
                                   np.ones((SLOTS, T, SKILLED), dtype), f(SLOTS, SKILLED))
    return buffers.SequenceStores(skilled, buffers.OffPolicyStore(traj, np.ones((SLOTS, OFF), dtype)),
                                  np.array([True, True, False]))


def _params(dtype=jnp.float32):
    ac = networks.init_actor_critic(jax.random.PRNGKey(0), OBS, ACT, (5,), 0.5)
    value = meta.init_value_heads(jax.random.PRNGKey(1), OBS, (5,), SLOTS)
    return jax.tree.map(lambda x: x.astype(dtype), (ac.policy, value))


@pytest.mark.parametrize("first_order", [False, True])
def test_meta_gradient_matches_finite_differences(first_order, check_meta_gradient):
    # Importance weights are constants by design (no gradient through ρ), so the loss is an exact function of θ
    # only without them; with them, finite differences would also move ρ.
    config = dataclasses.replace(CONFIG, importance_sampling=False)
    with jax.enable_x64(True):
        stores = jax.tree.map(lambda x: jnp.asarray(x), _stores(0, np.float64))
        policy, value = _params(jnp.float64)
        batches = meta.sample_batches(config, stores, jax.random.PRNGKey(2))
        loss = lambda p: meta.meta_loss(config, p, value, batches, stores.task_valid)  # noqa: E731
        grad = jax.grad(lambda p: meta.meta_loss(dataclasses.replace(config, first_order=first_order), p, value,
                                                 batches, stores.task_valid))(policy)
        check_meta_gradient(loss, grad, policy, lambda tree: tree, eps=1e-5, rtol=1e-5, first_order=first_order)


def test_second_order_differs_from_first_order():
    stores = _stores(1)
    policy, value = _params()
    batches = meta.sample_batches(CONFIG, stores, jax.random.PRNGKey(0))
    grads = [jax.grad(meta.meta_loss, argnums=1)(dataclasses.replace(CONFIG, first_order=fo), policy, value, batches,
                                                 stores.task_valid) for fo in (False, True)]
    diff = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(*map(jax.tree.leaves, grads)))
    assert diff > 1e-4


def test_masked_tasks_change_nothing():
    stores = _stores(2)
    policy, value = _params()
    other = _stores(99)
    # Slot 2 is unseen; give it entirely different (and even NaN) data.
    garbage = jax.tree.map(lambda a, b: np.concatenate([a[:2], b[2:]]), stores, other)
    garbage = garbage._replace(task_valid=stores.task_valid,
                               skilled=garbage.skilled._replace(obs=garbage.skilled.obs.copy()))
    garbage.skilled.obs[2] = np.nan
    for cfg in (CONFIG, dataclasses.replace(CONFIG, importance_sampling=False, vtrace_baseline=False)):
        b1 = meta.sample_batches(cfg, stores, jax.random.PRNGKey(0))
        b2 = meta.sample_batches(cfg, garbage, jax.random.PRNGKey(0))
        l1, g1 = jax.value_and_grad(meta.meta_loss, argnums=1)(cfg, policy, value, b1, stores.task_valid)
        l2, g2 = jax.value_and_grad(meta.meta_loss, argnums=1)(cfg, policy, value, b2, garbage.task_valid)
        chex.assert_trees_all_close((l1, g1), (l2, g2), rtol=1e-6)
        assert np.isfinite(float(l2))


def test_meta_training_lowers_the_outer_bc_loss():
    stores = _stores(3)
    policy, value = _params()
    p_opt, v_opt = meta.optimizers(CONFIG)
    state = meta.MetaState(policy, value, p_opt.init(policy), v_opt.init(value))
    batches = meta.sample_batches(CONFIG, stores, jax.random.PRNGKey(7))
    before = meta.meta_loss(CONFIG, policy, value, batches, stores.task_valid)
    calls = []
    hook = progress.host(lambda m: calls.append((int(m["task"]), int(m["meta_step"]), int(m["meta_steps"]),
                                                 float(m["bc_loss"]))))
    report = progress.with_fields(hook, task=jnp.int32(4))
    new, stats = jax.jit(lambda s, r: meta.meta_train(CONFIG, s, stores, r, progress_fn=report))(
        state, jax.random.PRNGKey(1))
    losses = stats.bc_loss
    jax.effects_barrier()
    after = meta.meta_loss(CONFIG, new.policy, new.value, batches, stores.task_valid)
    assert float(after) < float(before) - 0.05, (before, after)
    steps = CONFIG.num_meta_steps * CONFIG.num_outer_steps
    chex.assert_shape(losses, (steps,))
    assert np.all(np.isfinite(losses))
    # The progress hook sees every outer update, in order, with the loss that update computed.
    assert [c[:3] for c in sorted(calls, key=lambda c: c[1])] == [(4, i + 1, steps) for i in range(steps)]
    np.testing.assert_allclose([c[3] for c in sorted(calls, key=lambda c: c[1])], losses, rtol=1e-6)


def _reference_gradients(config, policy, value, stores, rng):
    """value_and_grad of the mean over valid slots of every slot's (BC + value l2), all slots at once."""
    batches = meta._zero_unseen(meta.sample_batches(config, stores, rng), stores.task_valid)
    valid = jnp.asarray(stores.task_valid, jnp.float32)

    def total(p, v):
        objective, stats = jax.vmap(lambda s, b: meta.slot_objective(config, p, v, s, b))(
            jnp.arange(SLOTS), batches)
        bc = stats.bc_loss
        return jnp.sum(objective * valid) / jnp.sum(valid), jnp.sum(bc * valid) / jnp.sum(valid)

    (_, bc), grads = jax.value_and_grad(total, argnums=(0, 1), has_aux=True)(policy, value)
    return bc, grads


@pytest.mark.parametrize("chunk", [1, 2, 3])
@pytest.mark.parametrize("valid", [(True, True, False), (True, False, True)])
def test_slot_loop_equals_all_slots_at_once(chunk, valid):
    stores = _stores(4)._replace(task_valid=np.array(valid))
    nan_slot = valid.index(False)
    stores.skilled.obs[nan_slot] = np.nan  # unseen slots may hold anything
    stores.offpolicy.traj.obs[nan_slot] = np.nan
    policy, value = _params()
    config = dataclasses.replace(CONFIG, task_chunk=chunk)
    stats, g_policy, g_value = jax.jit(lambda p, v: meta.meta_gradients(config, p, v, stores,
                                                                        jax.random.PRNGKey(5)))(policy, value)
    loss = stats.bc_loss
    clean = stores._replace(skilled=stores.skilled._replace(obs=np.nan_to_num(stores.skilled.obs)))
    clean = clean._replace(offpolicy=clean.offpolicy._replace(
        traj=clean.offpolicy.traj._replace(obs=np.nan_to_num(clean.offpolicy.traj.obs))))
    ref_loss, (ref_policy, ref_value) = _reference_gradients(config, policy, value, clean, jax.random.PRNGKey(5))
    chex.assert_trees_all_close((loss, g_policy, g_value), (ref_loss, ref_policy, ref_value), rtol=1e-5, atol=1e-6)
    # The BC loss in meta_loss form agrees too, and the value gradient is not trivially zero.
    batches = meta.sample_batches(config, clean, jax.random.PRNGKey(5))
    np.testing.assert_allclose(float(meta.meta_loss(config, policy, value, batches, clean.task_valid)), float(loss),
                               rtol=1e-5)
    assert float(jnp.max(jnp.abs(g_value[0]["w"]))) > 0


def test_bc_and_value_losses_do_not_cross():
    # Advantages and targets are constants: the BC loss has no value gradient, the value l2 no policy gradient.
    stores = _stores(5)
    policy, value = _params()
    batch = jax.tree.map(lambda x: x[0], meta.sample_batches(CONFIG, stores, jax.random.PRNGKey(0)))
    bc_grad_value = jax.grad(lambda v: meta.slot_objective(CONFIG, policy, v, 0, batch)[1].bc_loss)(value)
    l2_grad_policy = jax.grad(lambda p: meta.slot_objective(CONFIG, p, value, 0, batch)[1].value_l2)(policy)
    for leaf in jax.tree.leaves((bc_grad_value, l2_grad_policy)):
        assert float(jnp.max(jnp.abs(leaf))) == 0.0


def test_slot_sampling_does_not_depend_on_other_slots():
    stores = _stores(6)
    all_slots = meta.sample_batches(CONFIG, stores, jax.random.PRNGKey(3))
    one = meta._slot_batches(CONFIG, stores, jax.random.PRNGKey(3), jnp.array([1]))
    chex.assert_trees_all_equal(jax.tree.map(lambda x: x[1], all_slots), jax.tree.map(lambda x: x[0], one))


def _meta_state(policy, value, config):
    p_opt, v_opt = meta.optimizers(config)
    return meta.MetaState(policy, value, p_opt.init(policy), v_opt.init(value))


def test_sequential_outer_update_with_one_task_equals_the_mean():
    # One seen task: the mean over tasks is that task, and both readings draw the same batches per outer step.
    stores = _stores(8)._replace(task_valid=np.array([True, False, False]))
    policy, value = _params()
    config = dataclasses.replace(CONFIG, num_meta_steps=3, num_outer_steps=2)
    state = _meta_state(policy, value, config)
    run = lambda c: jax.jit(lambda s: meta.meta_train(c, s, stores, jax.random.PRNGKey(9)))(state)  # noqa: E731
    chex.assert_trees_all_close(run(config), run(dataclasses.replace(config, outer_update="sequential")),
                                rtol=1e-5, atol=1e-6)


def test_sequential_outer_update_follows_algorithm_1():
    # Per meta step n: task j = 0, 1 in order, K Adam steps on task j alone, step (n, k) drawing task j's batches
    # from the n·K + k-th key. A Python loop of single-task steps is the reference.
    stores = _stores(9)._replace(task_valid=np.array([True, True, False]))
    policy, value = _params()
    config = dataclasses.replace(CONFIG, num_meta_steps=2, num_outer_steps=2, outer_update="sequential")
    state = _meta_state(policy, value, config)
    calls = []
    hook = progress.host(lambda m: calls.append((int(m["meta_step"]), int(m["meta_steps"]))))
    new, stats = jax.jit(lambda s: meta.meta_train(config, s, stores, jax.random.PRNGKey(4), progress_fn=hook))(state)
    losses = stats.bc_loss
    jax.effects_barrier()
    p_opt, v_opt = meta.optimizers(config)
    keys = jax.random.split(jax.random.PRNGKey(4), 4).reshape(2, 2, -1)
    ref, ref_losses = state, np.zeros((2, 2))
    grad = jax.jit(lambda p, v, k, j: meta.slot_gradients(config, p, v, stores, k, j))
    for n in range(2):
        for j in range(2):
            for k in range(2):
                stats_j, g, vg = grad(ref.policy, ref.value, keys[n, k], j)
                loss = stats_j.bc_loss
                up, popt = p_opt.update(g, ref.policy_opt, ref.policy)
                vup, vopt = v_opt.update(vg, ref.value_opt, ref.value)
                ref = meta.MetaState(optax.apply_updates(ref.policy, up), optax.apply_updates(ref.value, vup), popt,
                                     vopt)
                ref_losses[n, k] += float(loss) / 2
    chex.assert_trees_all_close(new, ref, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(losses, ref_losses.reshape(-1), rtol=1e-5)
    # It differs from the mean reading (θ moves between tasks), and reports once per meta step.
    mean = jax.jit(lambda s: meta.meta_train(dataclasses.replace(config, outer_update="mean"), s, stores,
                                             jax.random.PRNGKey(4)))(state)[0]
    assert float(jnp.max(jnp.abs(mean.policy["mean"][0]["w"] - new.policy["mean"][0]["w"]))) > 1e-4
    assert sorted(calls) == [(2, 4), (4, 4)]


@pytest.mark.parametrize("field,value", [("inner_learning_rate", -0.1), ("num_meta_steps", -1),
                                         ("inner_trajectories", 0), ("discount", 0.0), ("task_chunk", -1),
                                         ("outer_update", "average"), ("outer_loss", "mse"),
                                         ("inner_ratio_clip", 1.0)])
def test_bad_meta_config_names_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        meta.MetaConfig(**{field: value})


def test_the_inner_clip_is_an_option_of_the_unweighted_inner_step():
    meta.MetaConfig(importance_sampling=False, vtrace_baseline=False, inner_ratio_clip=0.2)
    with pytest.raises(ValueError, match="inner_ratio_clip"):
        meta.MetaConfig(importance_sampling=True, inner_ratio_clip=0.2)


def _slot_batch(seed, config=CONFIG):
    stores = _stores(seed)
    return stores, jax.tree.map(lambda x: x[0], meta.sample_batches(config, stores, jax.random.PRNGKey(0)))


@pytest.mark.parametrize("outer_loss", ["nll", "mean_mse"])
def test_the_inner_gain_is_the_outer_loss_before_the_inner_step_minus_after(outer_loss):
    config = dataclasses.replace(CONFIG, outer_loss=outer_loss)
    _, batch = _slot_batch(13)
    policy, value = _params()
    _, stats = meta.slot_objective(config, policy, value, 0, batch)
    before = meta.outer_loss(config, policy, batch.skilled_obs, batch.skilled_action, batch.skilled_valid)
    adapted = meta.outer_loss(config, _adapted(config, policy, value, batch), batch.skilled_obs,
                              batch.skilled_action, batch.skilled_valid)
    np.testing.assert_allclose(float(stats.bc_loss), float(adapted), rtol=1e-6)
    np.testing.assert_allclose(float(stats.inner_gain), float(before - adapted), rtol=1e-5, atol=1e-7)
    assert abs(float(stats.inner_gain)) > 1e-4  # the inner step moves the outer loss


def _adapted(config, policy, value, batch):
    """φ = θ + α ∇_θ J(θ), by jax.grad of the inner objective written out (advantages as constants)."""
    off = batch.off
    head = meta.head_params(value, 0)
    values = networks.value_apply(head, networks.normalize_obs(policy, off.traj.obs))
    bootstrap = networks.value_apply(head, networks.normalize_obs(policy, off.traj.last_obs))
    log_prob = networks.GAUSSIAN.log_prob(policy, off.traj.obs, off.traj.action)
    advantages, _, _ = meta._vtrace_terms(config, log_prob, values, bootstrap, off)
    mask = off.traj.valid * off.mask[None, :]
    objective = lambda p: masked_mean(networks.GAUSSIAN.log_prob(p, off.traj.obs, off.traj.action) * advantages,  # noqa
                                      mask)
    return jax.tree.map(lambda p, g: p + config.inner_learning_rate * g, policy, jax.grad(objective)(policy))


def test_with_no_inner_step_the_gain_is_exactly_zero():
    """Law: α = 0 makes φ_j = θ, so every gain the meta step reports (per outer step and per slot) is exactly 0."""
    config = dataclasses.replace(CONFIG, inner_learning_rate=0.0, num_meta_steps=3)
    stores = _stores(14)
    policy, value = _params()
    stats, _, _ = meta.meta_gradients(config, policy, value, stores, jax.random.PRNGKey(3))
    assert float(stats.inner_gain) == 0.0
    per_slot = meta.slot_diagnostics(config, policy, value, stores)
    np.testing.assert_array_equal(np.asarray(per_slot.inner_gain)[:2], 0.0)
    assert np.isnan(float(per_slot.inner_gain[2]))  # unseen
    _, steps = meta.meta_train(config, _meta_state(policy, value, config), stores, jax.random.PRNGKey(4))
    np.testing.assert_array_equal(np.asarray(steps.inner_gain), 0.0)
    with_step, _, _ = meta.meta_gradients(CONFIG, policy, value, stores, jax.random.PRNGKey(3))
    assert float(with_step.inner_gain) != 0.0


def test_the_mean_squared_error_outer_loss_keeps_the_std_out_of_the_meta_step():
    config = dataclasses.replace(CONFIG, outer_loss="mean_mse")
    stores, batch = _slot_batch(15, config)
    policy, value = _params()
    mean, _ = networks.GAUSSIAN.dist(policy, batch.skilled_obs)
    by_hand = masked_mean(jnp.mean(jnp.square(mean - batch.skilled_action), axis=-1), batch.skilled_valid)
    np.testing.assert_allclose(float(meta.mean_mse_loss(policy, batch.skilled_obs, batch.skilled_action,
                                                        batch.skilled_valid)), float(by_hand), rtol=1e-6)
    grads = {loss: jax.grad(lambda p: meta.slot_objective(dataclasses.replace(CONFIG, outer_loss=loss), p, value, 0,
                                                          batch)[0])(policy) for loss in ("nll", "mean_mse")}
    assert float(jnp.max(jnp.abs(grads["nll"]["log_std"]))) > 0
    np.testing.assert_array_equal(np.asarray(grads["mean_mse"]["log_std"]), 0.0)
    assert float(jnp.max(jnp.abs(grads["mean_mse"]["mean"][0]["w"]))) > 0
    state, _ = meta.meta_train(config, _meta_state(policy, value, config), stores, jax.random.PRNGKey(5))
    np.testing.assert_array_equal(np.asarray(state.policy["log_std"]), np.asarray(policy["log_std"]))
    assert float(jnp.max(jnp.abs(state.policy["mean"][0]["w"] - policy["mean"][0]["w"]))) > 0


def test_the_authors_ppo_inner_step_weights_by_the_ratio_clipped_to_one_plus_minus_epsilon():
    base = dataclasses.replace(CONFIG, importance_sampling=False, vtrace_baseline=False)
    _, batch = _slot_batch(16, base)
    policy, _ = _params()
    off = batch.off
    log_prob = networks.GAUSSIAN.log_prob(policy, off.traj.obs, off.traj.action)
    values, bootstrap = 0.1 * jnp.ones_like(log_prob), jnp.zeros_like(off.traj.last_obs[:, 0])
    plain, targets, ones = meta._vtrace_terms(base, log_prob, values, bootstrap, off)
    clipped, targets_c, weights = meta._vtrace_terms(dataclasses.replace(base, inner_ratio_clip=0.2), log_prob,
                                                     values, bootstrap, off)
    ratio = np.exp(np.asarray(log_prob - off.traj.log_prob))
    assert np.any(ratio < 0.8) and np.any(ratio > 1.2)  # the clip binds on both sides in this batch
    np.testing.assert_array_equal(np.asarray(ones), 1.0)
    np.testing.assert_allclose(np.asarray(weights), np.clip(ratio, 0.8, 1.2), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(clipped), np.asarray(weights * plain), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(targets_c), np.asarray(targets))


@pytest.mark.parametrize("vtrace_baseline", [False, True])
def test_standardised_inner_advantages(vtrace_baseline):
    """``normalize_advantages`` standardises the raw advantages over the task's valid samples, then weights them
    by the same clipped importance weights as the raw reading; an affine change of the rewards' scale and zero
    leaves the standardised unweighted advantages unchanged (with V from the same rewards' scale: zero here)."""
    stores = _stores(8)
    policy, value = _params()
    batch = jax.tree.map(lambda x: x[0], meta.sample_batches(CONFIG, stores, jax.random.PRNGKey(0)))
    off = batch.off._replace(mask=batch.off.mask.at[0].set(0.0))  # one trajectory masked out
    log_prob = networks.GAUSSIAN.log_prob(policy, off.traj.obs, off.traj.action)
    values, bootstrap = jnp.zeros_like(log_prob), jnp.zeros_like(off.traj.last_obs[:, 0])
    mask = off.traj.valid * off.mask[None, :]
    for importance_sampling in (False, True):
        base = dataclasses.replace(CONFIG, vtrace_baseline=vtrace_baseline, importance_sampling=importance_sampling)
        raw, targets, _ = meta._vtrace_terms(base, log_prob, values, bootstrap, off)
        normed, targets_n, _ = meta._vtrace_terms(dataclasses.replace(base, normalize_advantages=True), log_prob,
                                               values, bootstrap, off)
        np.testing.assert_allclose(targets, targets_n)
        weights = (jnp.minimum(jnp.exp(log_prob - off.traj.log_prob), base.pg_rho_bar) if importance_sampling
                   else jnp.ones_like(log_prob))
        unweighted = normed / weights
        assert abs(float(masked_mean(unweighted, mask))) < 1e-5
        np.testing.assert_allclose(float(jnp.sqrt(masked_mean(jnp.square(unweighted), mask))), 1.0, rtol=1e-4)
        # Proportional to the raw advantages (the same weights multiply both) up to the shift and scale.
        raw_unweighted = raw / weights
        mean = masked_mean(raw_unweighted, mask)
        std = jnp.sqrt(masked_mean(jnp.square(raw_unweighted - mean), mask))
        np.testing.assert_allclose(np.asarray(unweighted * mask), np.asarray((raw_unweighted - mean) / std * mask),
                                   rtol=1e-4, atol=1e-5)
    if not vtrace_baseline:
        config = dataclasses.replace(CONFIG, vtrace_baseline=False, importance_sampling=False,
                                     normalize_advantages=True)
        a, _, _ = meta._vtrace_terms(config, log_prob, values, bootstrap, off)
        scaled = off._replace(traj=off.traj._replace(reward=7.0 * off.traj.reward))
        b, _, _ = meta._vtrace_terms(config, log_prob, values, bootstrap, scaled)
        np.testing.assert_allclose(np.asarray(a * mask), np.asarray(b * mask), rtol=1e-4, atol=1e-5)


def _flat(config, prefix=""):
    out = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            out.update(_flat(value, f"{prefix}{f.name}."))
        else:
            out[prefix + f.name] = value
    return out


@pytest.mark.parametrize("family", ["point_goal", "cheetah_vel", "ant_goal", "ant_dir", "metaworld"])
def test_every_rung_of_the_ladder_adds_exactly_one_feature(family):
    from jcomps import methods

    named = [feature for _, _, feature in methods.LADDER]
    assert sorted(named) == sorted(methods.LADDER_FEATURES)  # every feature is a rung of its own
    for lower, upper, feature in methods.LADDER:
        a, b = _flat(methods.default_config(lower, family)), _flat(methods.default_config(upper, family))
        assert a.keys() == b.keys()
        differ = {k for k in a if a[k] != b[k]}
        assert differ, (lower, upper)
        assert differ <= set(methods.LADDER_FEATURES[feature]), (lower, upper, differ)
    # The standardisation of the inner advantages is the same on every rung.
    values = {methods.default_config(m, family).meta.normalize_advantages
              for m in ("gmps", "gmps_ppo", "gmps_ppo_is", "gmps_ppo_is_x2", "comps")}
    assert values == {methods.STANDARDISED_INNER_ADVANTAGES}


def _constant_reward_stores(reward, policy, seed=11):
    """Stores whose every step pays ``reward``, never terminating, collected by ``policy`` itself (ρ = 1)."""
    stores = _stores(seed)
    traj = stores.offpolicy.traj
    log_prob = jax.vmap(lambda o, a: networks.GAUSSIAN.log_prob(policy, o, a))(traj.obs, traj.action)
    traj = traj._replace(reward=np.full_like(traj.reward, reward), log_prob=np.asarray(log_prob))
    return stores._replace(offpolicy=stores.offpolicy._replace(traj=traj))


@pytest.mark.parametrize("importance_sampling", [False, True])
def test_a_head_learns_the_value_of_a_constant_reward_in_the_rl_steps_units(importance_sampling):
    # Law: with reward r at every step, reward scale c and discount γ, V = c·r/(1 − γ) everywhere (the bootstrap
    # at the time limit included). From its random initialisation the head gets there within the configured
    # meta steps, in the RL step's units (c), whatever the inner step's weighting.
    policy, value = _params()
    stores = _constant_reward_stores(10.0, policy)
    config = dataclasses.replace(CONFIG, discount=0.5, reward_scale=0.1, value_learning_rate=0.03,
                                 num_meta_steps=25, num_outer_steps=5, importance_sampling=importance_sampling,
                                 vtrace_baseline=importance_sampling, outer_learning_rate=1e-4)
    new, stats = jax.jit(lambda s: meta.meta_train(config, s, stores, jax.random.PRNGKey(0)))(
        _meta_state(policy, value, config))
    target = 0.1 * 10.0 / (1 - 0.5)
    for slot in (0, 1):  # the seen slots
        v = meta._head(new.value, networks.normalize_obs(new.policy, stores.offpolicy.traj.obs[slot]), slot)
        assert abs(float(jnp.mean(v)) - target) < 0.03 * target, (slot, v)  # from ~0 at initialisation
        np.testing.assert_allclose(np.asarray(v), target, rtol=0.1)
    assert float(stats.value_l2[-1]) < 1e-3 * target ** 2 < float(stats.value_l2[0])


def test_a_fitted_head_is_not_moved_by_the_first_update():
    # A head that already predicts c·r/(1 − γ) has zero TD errors, so its l2 gradient is exactly zero and Adam
    # leaves it where it is, while the policy moves.
    policy, value = _params()
    stores = _constant_reward_stores(10.0, policy)
    fitted = jax.tree.map(lambda x: x.at[0].set(0.0), value)  # head 0: zero weights ...
    fitted[-1]["b"] = fitted[-1]["b"].at[0].set(2.0)            # ... and V ≡ 0.1·10/(1 − 0.5) = 2
    config = dataclasses.replace(CONFIG, discount=0.5, reward_scale=0.1, num_meta_steps=1, num_outer_steps=1)
    new, _ = jax.jit(lambda s: meta.meta_train(config, s, stores, jax.random.PRNGKey(0)))(
        _meta_state(policy, fitted, config))
    chex.assert_trees_all_equal(meta.head_params(new.value, 0), meta.head_params(fitted, 0))
    assert float(jnp.max(jnp.abs(meta.head_params(new.value, 1)[0]["w"] - meta.head_params(fitted, 1)[0]["w"]))) > 0
    assert float(jnp.max(jnp.abs(new.policy["mean"][0]["w"] - policy["mean"][0]["w"]))) > 0


def test_slot_diagnostics_measure_the_heads_fit_and_the_weights():
    policy, value = _params()
    stores = _constant_reward_stores(10.0, policy)._replace(task_valid=np.array([True, False, False]))
    # Rewards that vary along the trajectory, so that the returns have a spread to explain.
    traj = stores.offpolicy.traj
    stores = stores._replace(offpolicy=stores.offpolicy._replace(
        traj=traj._replace(reward=np.cumsum(np.ones_like(traj.reward), axis=1))))
    config = dataclasses.replace(CONFIG, reward_scale=0.5)
    stats = jax.jit(lambda p, v: meta.slot_diagnostics(config, p, v, stores))(policy, value)
    chex.assert_shape(stats.value_ev, (SLOTS,))
    assert np.all(np.isnan(np.asarray(stats.value_ev)[1:]))  # unseen slots
    # On the behaviour policy's own data every clipped weight is 1.
    np.testing.assert_allclose(float(stats.rho[0]), 1.0, rtol=1e-5)
    # A head that predicts the returns exactly: explained variance 1 and no bias. Its returns, by hand:
    off = jax.tree.map(lambda x: x[0], stores.offpolicy)
    v = meta._head(value, networks.normalize_obs(policy, off.traj.obs), 0)
    boot = meta._head(value, networks.normalize_obs(policy, off.traj.last_obs), 0)
    returns = np.zeros_like(np.asarray(v))
    acc = np.asarray(boot)
    for t in reversed(range(T)):
        acc = 0.5 * np.asarray(off.traj.reward[t]) + config.discount * acc
        returns[t] = acc
    ev = 1 - np.var(returns - np.asarray(v)) / np.var(returns)
    np.testing.assert_allclose(float(stats.value_ev[0]), ev, rtol=1e-4)
    np.testing.assert_allclose(float(stats.value_bias[0]), np.mean(np.asarray(v) - returns), rtol=1e-4)
    np.testing.assert_allclose(float(stats.return_std[0]), np.std(returns), rtol=1e-4)


def test_the_reset_reading_starts_each_meta_phase_with_fresh_adam_states():
    stores = _stores(12)
    policy, value = _params()
    config = dataclasses.replace(CONFIG, num_meta_steps=2, optimizer_state="carry")
    used = jax.jit(lambda s: meta.meta_train(config, s, stores, jax.random.PRNGKey(1)))(
        _meta_state(policy, value, config))[0]  # Adam moments no longer zero
    carry = jax.jit(lambda s: meta.meta_train(config, s, stores, jax.random.PRNGKey(2)))(used)[0]
    reset_config = dataclasses.replace(config, optimizer_state="reset")
    reset = jax.jit(lambda s: meta.meta_train(reset_config, s, stores, jax.random.PRNGKey(2)))(used)[0]
    fresh = jax.jit(lambda s: meta.meta_train(reset_config, s, stores, jax.random.PRNGKey(2)))(
        _meta_state(used.policy, used.value, config))[0]
    chex.assert_trees_all_close(reset, fresh, rtol=1e-6)
    assert float(jnp.max(jnp.abs(carry.policy["mean"][0]["w"] - reset.policy["mean"][0]["w"]))) > 1e-6


def test_fitting_a_new_head_recovers_the_returns_of_its_data():
    # Law: with γ = 0 the return of a step is its (scaled) reward; rewards that are a smooth function of the
    # observation are recovered by the fit (explained variance near 1, no bias), the other heads untouched.
    policy, value = _params()
    stores = _stores(13)
    traj = stores.offpolicy.traj
    stores = stores._replace(offpolicy=stores.offpolicy._replace(traj=traj._replace(reward=2.0 * traj.obs[..., 0])))
    config = dataclasses.replace(CONFIG, discount=1e-6, reward_scale=0.5, value_fit_steps=300,
                                 value_fit_learning_rate=1e-2)
    off = jax.tree.map(lambda x: x[1], stores.offpolicy)
    fitted = jax.jit(lambda v: meta.fit_head(config, policy, v, 1, off))(value)
    stats = jax.jit(lambda v: meta.slot_diagnostics(config, policy, v, stores))(fitted)
    before = jax.jit(lambda v: meta.slot_diagnostics(config, policy, v, stores))(value)
    assert float(stats.value_ev[1]) > 0.95 and float(before.value_ev[1]) < 0.5
    assert abs(float(stats.value_bias[1])) < 0.05 * float(stats.return_std[1])
    for slot in (0, 2):
        chex.assert_trees_all_equal(meta.head_params(fitted, slot), meta.head_params(value, slot))
    no_fit = dataclasses.replace(config, value_fit_steps=0)
    chex.assert_trees_all_equal(meta.fit_head(no_fit, policy, value, 1, off), value)


def test_learnt_inner_step_sizes_start_at_alpha_and_are_meta_learnt_per_parameter():
    """Meta-SGD: at its initialisation (every size α) the objective and its gradient in θ are the fixed-α ones; the
    outer update then moves the sizes, one per parameter, and leaves the fixed reading without any."""
    learnt = dataclasses.replace(CONFIG, inner_step_sizes="learnt")
    stores, batch = _slot_batch(16)
    policy, value = _params()
    with_sizes = meta.with_inner_step_sizes(learnt, policy)
    assert meta.with_inner_step_sizes(CONFIG, policy) is policy
    assert meta.with_inner_step_sizes(learnt, with_sizes) is with_sizes  # already has them: kept as they are
    chex.assert_trees_all_equal_shapes(with_sizes["inner_lr"], {k: policy[k] for k in meta.STEPPED})
    fixed_loss, fixed_grad = jax.value_and_grad(lambda p: meta.slot_objective(CONFIG, p, value, 0, batch)[0])(policy)
    loss, grad = jax.value_and_grad(lambda p: meta.slot_objective(learnt, p, value, 0, batch)[0])(with_sizes)
    np.testing.assert_allclose(float(loss), float(fixed_loss), rtol=1e-6)
    chex.assert_trees_all_close({k: grad[k] for k in meta.STEPPED}, {k: fixed_grad[k] for k in meta.STEPPED},
                                rtol=1e-5, atol=1e-7)
    assert float(jnp.max(jnp.abs(grad["inner_lr"]["mean"][0]["w"]))) > 0  # the outer loss reaches each size
    # A size scales its own parameter's step: zero one layer's sizes and that layer is not adapted.
    frozen = {**with_sizes, "inner_lr": {**with_sizes["inner_lr"], "mean": [
        jax.tree.map(jnp.zeros_like, with_sizes["inner_lr"]["mean"][0]), *with_sizes["inner_lr"]["mean"][1:]]}}
    off = batch.off
    head = meta.head_params(value, 0)
    log_prob, vjp = jax.vjp(lambda p: networks.GAUSSIAN.log_prob(p, off.traj.obs, off.traj.action), frozen)
    values = networks.value_apply(head, networks.normalize_obs(frozen, off.traj.obs))
    bootstrap = networks.value_apply(head, networks.normalize_obs(frozen, off.traj.last_obs))
    advantages, _, _ = meta._vtrace_terms(learnt, log_prob, values, bootstrap, off)
    adapted = meta.adapt(learnt, frozen, off, advantages, vjp)
    chex.assert_trees_all_equal(adapted["mean"][0], frozen["mean"][0])
    assert float(jnp.max(jnp.abs(adapted["mean"][1]["w"] - frozen["mean"][1]["w"]))) > 0
    state, _ = meta.meta_train(learnt, _meta_state(with_sizes, value, learnt), stores, jax.random.PRNGKey(6))
    moved = state.policy["inner_lr"]["mean"][0]["w"] - CONFIG.inner_learning_rate
    assert float(jnp.max(jnp.abs(moved))) > 0 and float(jnp.std(moved)) > 0  # per parameter, not one shared size
