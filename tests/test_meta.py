"""Tests of the meta step: the meta-gradient against finite differences, second vs first order, masked slots,
and that meta training lowers the outer behaviour-cloning loss."""

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from jcomps import buffers, meta, networks, progress
from jcomps.acting import Trajectory
from jcomps.numerics import masked_mean

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
    new, losses = jax.jit(lambda s, r: meta.meta_train(CONFIG, s, stores, r, progress_fn=report))(
        state, jax.random.PRNGKey(1))
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
        objective, (bc, _) = jax.vmap(lambda s, b: meta.slot_objective(config, p, v, s, b))(
            jnp.arange(SLOTS), batches)
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
    loss, g_policy, g_value = jax.jit(lambda p, v: meta.meta_gradients(config, p, v, stores, jax.random.PRNGKey(5)))(
        policy, value)
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
    bc_grad_value = jax.grad(lambda v: meta.slot_objective(CONFIG, policy, v, 0, batch)[1][0])(value)
    l2_grad_policy = jax.grad(lambda p: meta.slot_objective(CONFIG, p, value, 0, batch)[1][1])(policy)
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
    new, losses = jax.jit(lambda s: meta.meta_train(config, s, stores, jax.random.PRNGKey(4), progress_fn=hook))(state)
    jax.effects_barrier()
    p_opt, v_opt = meta.optimizers(config)
    keys = jax.random.split(jax.random.PRNGKey(4), 4).reshape(2, 2, -1)
    ref, ref_losses = state, np.zeros((2, 2))
    grad = jax.jit(lambda p, v, k, j: meta.slot_gradients(config, p, v, stores, k, j))
    for n in range(2):
        for j in range(2):
            for k in range(2):
                loss, g, vg = grad(ref.policy, ref.value, keys[n, k], j)
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


@pytest.mark.parametrize("field,value", [("inner_learning_rate", 0.0), ("num_meta_steps", -1),
                                         ("inner_trajectories", 0), ("discount", 0.0), ("task_chunk", -1),
                                         ("outer_update", "average")])
def test_bad_meta_config_names_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        meta.MetaConfig(**{field: value})


@pytest.mark.parametrize("vtrace_baseline", [False, True])
def test_standardised_inner_advantages(vtrace_baseline):
    """``normalize_advantages`` standardises the raw advantages over the task's valid samples, then weights them
    by the same clipped importance weights as the raw reading; an affine change of the rewards' scale and zero
    leaves the standardised unweighted advantages unchanged (with V from the same rewards' scale: zero here)."""
    stores = _stores(8)
    policy, value = _params()
    batch = jax.tree.map(lambda x: x[0], meta.sample_batches(CONFIG, stores, jax.random.PRNGKey(0)))
    off = batch.off._replace(mask=batch.off.mask.at[0].set(0.0))  # one trajectory masked out
    log_prob = networks.policy_log_prob(policy, off.traj.obs, off.traj.action)
    values, bootstrap = jnp.zeros_like(log_prob), jnp.zeros_like(off.traj.last_obs[:, 0])
    mask = off.traj.valid * off.mask[None, :]
    for importance_sampling in (False, True):
        base = dataclasses.replace(CONFIG, vtrace_baseline=vtrace_baseline, importance_sampling=importance_sampling)
        raw, targets = meta._vtrace_terms(base, log_prob, values, bootstrap, off)
        normed, targets_n = meta._vtrace_terms(dataclasses.replace(base, normalize_advantages=True), log_prob,
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
        a, _ = meta._vtrace_terms(config, log_prob, values, bootstrap, off)
        scaled = off._replace(traj=off.traj._replace(reward=7.0 * off.traj.reward))
        b, _ = meta._vtrace_terms(config, log_prob, values, bootstrap, scaled)
        np.testing.assert_allclose(np.asarray(a * mask), np.asarray(b * mask), rtol=1e-4, atol=1e-5)


def test_the_unweighted_rungs_standardise_and_the_weighted_do_not():
    from jcomps import methods

    for name, expected in [("gmps", True), ("gmps_ppo", True), ("gmps_ppo_is", False), ("comps", False)]:
        assert methods.default_config(name, "ant_goal").meta.normalize_advantages is expected, name
