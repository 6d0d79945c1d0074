"""Laws of the paper's other continual baselines: MAML+TL (the meta-gradient through the inner step) and
Progress & Compress (frozen knowledge base, EWC penalty, distillation, lateral gradients)."""

import dataclasses
import json

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jcomps import continual, envs, methods
from jcomps.methods import maml_tl, pnc
from jcomps.training import acting, networks, ppo

OBS, ACT, N = 3, 2, 12
TINY_PPO = ppo.PPOConfig(num_trajectories=2, num_updates=2, minibatch_size=16, hidden_sizes=(8, 8), budget=4)


def _batch(rng, policy, dtype):
    """A flat batch of N samples whose behaviour log-probabilities sit near π's (ratios well inside the clip)."""
    f = lambda *s: jnp.asarray(rng.normal(size=s), dtype)  # noqa: E731
    obs, action = f(N, OBS), f(N, ACT)
    log_prob = networks.GAUSSIAN.log_prob(policy, obs, action) + 0.01 * f(N)
    return {"obs": obs, "action": action, "log_prob": log_prob, "valid": jnp.ones((N,), dtype),
            "advantage": f(N), "target": f(N)}


def _maml_setup(dtype, first_order=False, inner_objective="vpg"):
    config = maml_tl.MAMLTLConfig(ppo=dataclasses.replace(TINY_PPO, hidden_sizes=(5,)), inner_learning_rate=0.5,
                                  first_order=first_order, inner_objective=inner_objective)
    params = networks.init_actor_critic(jax.random.PRNGKey(0), OBS, ACT, (5,), 0.5)
    params = jax.tree.map(lambda x: x.astype(dtype), params)
    params = params._replace(policy={**params.policy, "mean": [
        {"w": layer["w"] + 0.3 * jax.random.normal(jax.random.PRNGKey(i), layer["w"].shape, dtype), "b": layer["b"]}
        for i, layer in enumerate(params.policy["mean"])]})
    rng = np.random.default_rng(1)
    pre = _batch(rng, params.policy, dtype)
    adapted = maml_tl.inner_step(config, params.policy, pre)
    post = _batch(rng, adapted, dtype)
    return config, params, {"full": pre, "minibatch": pre}, post


@pytest.mark.parametrize("first_order,inner_objective", [(False, "vpg"), (True, "vpg"), (False, "lvc")])
def test_maml_meta_gradient_matches_finite_differences(first_order, inner_objective, check_meta_gradient):
    with jax.enable_x64(True):
        config, params, pre, post = _maml_setup(jnp.float64, inner_objective=inner_objective)
        loss = jax.jit(lambda p: maml_tl.outer_loss(config, p, pre, post)[0])
        fo_config = dataclasses.replace(config, first_order=first_order)
        grad = jax.jit(jax.grad(lambda p: maml_tl.outer_loss(fo_config, p, pre, post)[0]))(params)
        check_meta_gradient(loss, grad, params, lambda tree: tree.policy, eps=1e-6, rtol=1e-6,
                            first_order=first_order)


def test_maml_second_order_differs_from_first_order():
    grads = []
    for first_order in (False, True):
        config, params, pre, post = _maml_setup(jnp.float32, first_order)
        grads.append(jax.jit(jax.grad(lambda p: maml_tl.outer_loss(config, p, pre, post)[0]))(params).policy["mean"])
    diff = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(*map(jax.tree.leaves, grads)))
    assert diff > 1e-4


def test_maml_lvc_takes_the_same_step_at_the_behaviour_policy_with_more_curvature():
    """At the behaviour policy ProMP's objective has the vanilla one's gradient, so φ is the same; importance
    weights ≠ 1 give another step; the meta-gradient differs even on-policy (the ∇log π ∇log πᵀ Â term)."""
    vpg, params, pre, post = _maml_setup(jnp.float32)
    lvc = dataclasses.replace(vpg, inner_objective="lvc")
    full = pre["full"]  # its behaviour log-probs are π's plus noise of 0.01
    on_policy = {**full, "log_prob": networks.GAUSSIAN.log_prob(params.policy, full["obs"], full["action"])}
    step = lambda c, batch: maml_tl.inner_step(c, params.policy, batch)  # noqa: E731
    leaves = jax.tree.leaves
    max_diff = lambda a, b: max(float(jnp.max(jnp.abs(x - y))) for x, y in zip(leaves(a), leaves(b)))  # noqa: E731
    assert max_diff(step(vpg, on_policy), step(lvc, on_policy)) < 1e-5
    assert max_diff(step(vpg, full), step(lvc, full)) > 1e-5
    batch = {"full": on_policy, "minibatch": on_policy}
    grad = lambda c: jax.grad(lambda p: maml_tl.outer_loss(c, p, batch, post)[0])(params).policy["mean"]  # noqa: E731
    assert max_diff(grad(vpg), grad(lvc)) > 1e-4


def test_maml_inner_step_is_a_policy_gradient_ascent_step():
    config, params, pre, _ = _maml_setup(jnp.float32)
    full = pre["full"]
    adv = (full["advantage"] - full["advantage"].mean()) / (full["advantage"].std() + 1e-8)
    objective = lambda p: jnp.mean(networks.GAUSSIAN.log_prob(p, full["obs"], full["action"]) * adv)  # noqa: E731
    adapted = maml_tl.inner_step(config, params.policy, full)
    g = jax.grad(objective)(params.policy)
    expected = jax.tree.map(lambda p, d: p + config.inner_learning_rate * d, params.policy, g)
    for a, b in zip(jax.tree.leaves(adapted), jax.tree.leaves(expected)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    assert float(objective(adapted)) > float(objective(params.policy))  # a small ascent step raises J


# --- MAML+TL's evaluations: the adapted policy ---

MAML_PPO = dataclasses.replace(TINY_PPO, budget=2)


@pytest.fixture(scope="module")
def maml_chunk():
    """MAML+TL after two Point Goal tasks as the runner learns them, each task then its evaluations
    (``continual.learn_at``, ``continual.evaluate_task``, backward transfer on the previous task): (method, eval
    key, sequence, final state, ChunkMetrics [2])."""
    family = envs.make("point_goal")
    method = methods.make("maml_tl", family, maml_tl.MAMLTLConfig(ppo=MAML_PPO))
    seq = envs.sequence(family, num_tasks=2)
    key = jax.random.PRNGKey(5)
    learn = jax.jit(lambda s, i: continual.learn_at(method, s, seq, i))
    evaluate = jax.jit(lambda s, i: continual.evaluate_task(method, continual.EvalConfig(backward_tasks=1), s, seq,
                                                            i, key))
    state, per_task = method.init(jax.random.PRNGKey(0)), []
    for i in range(2):
        state, learnt = learn(state, jnp.int32(i))
        per_task.append(continual.chunk_metrics(learnt, evaluate(state, jnp.int32(i))))
    return method, key, seq, state, jax.tree.map(lambda *x: jnp.stack(x), *per_task)


def _task(seq, i):
    return jax.tree.map(lambda x: x[i], seq)


def _mean_return(method, policy, task, key):
    traj = acting.rollout(method.family, policy, task, key, MAML_PPO.num_trajectories)
    return jnp.mean(jnp.sum(traj.reward, axis=0))


def _max_diff(a, b):
    return max(float(jnp.max(jnp.abs(x - y))) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def test_maml_policy_for_is_the_inner_step_on_fresh_episodes_of_the_task(maml_chunk):
    method, _, seq, state, _ = maml_chunk
    key, theta = jax.random.PRNGKey(3), state.params.policy
    phi = jax.jit(lambda t: methods.base.policy_for(method, state, jnp.int32(0), t, key))

    @jax.jit
    def by_hand(task):
        traj = acting.rollout(method.family, theta, task, key, MAML_PPO.num_trajectories)
        return maml_tl.inner_step(method.config, theta, ppo.flat_batch(MAML_PPO, state.params, traj))

    phi0, phi1 = phi(_task(seq, 0)), phi(_task(seq, 1))
    chex.assert_trees_all_close(phi0, by_hand(_task(seq, 0)), rtol=1e-5, atol=1e-6)
    assert _max_diff(phi0, theta) > 1e-4  # the inner step moves θ …
    assert _max_diff(phi0, phi1) > 1e-4  # … on the evaluated task's data
    # with a vanishing inner step φ is θ
    tiny_step = methods.make("maml_tl", method.family, maml_tl.MAMLTLConfig(ppo=MAML_PPO, inner_learning_rate=1e-9))
    still = jax.jit(lambda t: methods.base.policy_for(tiny_step, state, jnp.int32(0), t, key))(_task(seq, 0))
    chex.assert_trees_all_close(still, theta, rtol=0, atol=1e-7)


def test_maml_backward_transfer_evaluates_the_adapted_policy(maml_chunk):
    """After task 1 the policy is evaluated on task 0 (``evaluate_task``'s keys: fold_in(fold_in(key, 1), 0) for
    the rollout, its fold_in 7 for ``policy_for``): φ's return, not θ's."""
    method, eval_key, seq, state, metrics = maml_chunk
    assert np.asarray(metrics.backward_valid).tolist() == [[False], [True]]
    key = jax.random.fold_in(jax.random.fold_in(eval_key, 1), 0)

    @jax.jit
    def returns(task):
        phi = methods.base.policy_for(method, state, jnp.int32(0), task, jax.random.fold_in(key, 7))
        return _mean_return(method, phi, task, key), _mean_return(method, state.params.policy, task, key)

    adapted, theta = returns(_task(seq, 0))
    np.testing.assert_allclose(float(metrics.backward_returns[1, 0]), float(adapted), rtol=1e-5)
    assert abs(float(adapted) - float(theta)) > 1e-3


def test_maml_adapt_runs_inner_steps_from_theta_one_batch_each(maml_chunk):
    """Entry 0 is θ zero-shot; entry 1 the policy after one inner step on entry 0's batch (``policy_for``'s φ
    with that key), the policy MAML reports after adaptation; later entries step on from there. The held-out
    meta-test runs it."""
    method, _, seq, state, _ = maml_chunk
    task, rng = _task(seq, 1), jax.random.PRNGKey(9)
    returns, success = jax.jit(lambda k: method.adapt(state, task, k, 3))(rng)
    assert returns.shape == success.shape == (3,)
    keys = jax.random.split(rng, 3)

    @jax.jit
    def by_hand():
        theta = state.params.policy
        phi1 = methods.base.policy_for(method, state, jnp.int32(0), task, keys[0])
        phi2 = maml_tl.adapt_on(method.config, method.family, state.params, phi1, task, keys[1])[0]
        return jnp.stack([_mean_return(method, p, task, k) for p, k in zip((theta, phi1, phi2), keys)])

    np.testing.assert_allclose(np.asarray(returns), np.asarray(by_hand()), rtol=1e-5)
    eval_config = continual.EvalConfig(heldout_iterations=1, heldout_budget=3)
    tasks = jax.tree.map(lambda x: x[:2], envs.held_out(method.family))
    held = jax.jit(lambda k: continual.heldout_adaptation(method, eval_config, state, tasks, k))(rng)
    direct = jax.jit(jax.vmap(lambda t, k: method.adapt(state, t, k, 3)))(tasks, jax.random.split(rng, 2))
    np.testing.assert_allclose(np.asarray(held.mean_return), np.asarray(direct[0][:, :2]), rtol=1e-5)
    assert held.iterations.shape == (2,)


# --- Progress & Compress ---

def _pnc_policies(seed=0):
    family = envs.make("point_goal")
    config = pnc.PNCConfig(ppo=TINY_PPO)
    kb = ppo.init_params(config.ppo, family, jax.random.PRNGKey(seed)).policy
    active, value = pnc.init_active(config, family, jax.random.PRNGKey(seed + 1), kb["obs_norm"])
    return family, config, kb, active, value


def test_lateral_connections_carry_gradient_into_the_active_column_only():
    family, _, kb, active, _ = _pnc_policies()
    obs = jax.random.normal(jax.random.PRNGKey(2), (7, family.obs_size))
    action = jax.random.normal(jax.random.PRNGKey(3), (7, family.action_size))
    grads = jax.grad(lambda p: jnp.sum(pnc.COLUMN.log_prob(p, obs, action)))(pnc.with_kb(active, kb))
    assert all(float(jnp.max(jnp.abs(g))) == 0.0 for g in jax.tree.leaves(grads["kb"]))
    assert all(float(jnp.max(jnp.abs(g))) > 0.0 for g in jax.tree.leaves(grads["adaptors"]))
    assert all(float(jnp.max(jnp.abs(g))) > 0.0 for g in jax.tree.leaves(grads["mean"]))
    # ... while the knowledge base does shape the active column's output through them.
    other_kb = ppo.init_params(TINY_PPO, family, jax.random.PRNGKey(9)).policy
    a = pnc.COLUMN.dist(pnc.with_kb(active, kb), obs)[0]
    b = pnc.COLUMN.dist(pnc.with_kb(active, other_kb), obs)[0]
    assert float(jnp.max(jnp.abs(a - b))) > 1e-4


def test_knowledge_base_is_unchanged_by_the_progress_phase():
    family, config, kb, active, value = _pnc_policies()
    params = networks.ActorCriticParams(pnc.with_kb(active, kb), value)
    optimizer = ppo.make_optimizer(config.ppo)
    step = jax.jit(lambda p, o: ppo.rl_step(config.ppo, family, p, o, envs.task_at(family, 0),
                                            jax.random.PRNGKey(4), stop_at_threshold=False, policy_fns=pnc.COLUMN))
    out = step(params, optimizer.init(params))
    for before, after in zip(jax.tree.leaves(kb), jax.tree.leaves(out.params.policy["kb"])):
        np.testing.assert_array_equal(before, after)
    moved = [float(jnp.max(jnp.abs(x - y))) for x, y in zip(jax.tree.leaves(active["adaptors"]),
                                                            jax.tree.leaves(out.params.policy["adaptors"]))]
    assert max(moved) > 0.0  # the adaptors learn


def test_ewc_penalty_is_zero_at_the_anchor_and_grows_with_fisher_weighted_distance():
    _, config, kb, _, _ = _pnc_policies()
    anchor = pnc.trainable(kb)
    fisher = jax.tree.map(lambda x: jnp.abs(jax.random.normal(jax.random.PRNGKey(5), x.shape)), anchor)
    direction = jax.tree.map(lambda x: jax.random.normal(jax.random.PRNGKey(6), x.shape), anchor)
    at = lambda t, f=fisher: float(pnc.ewc_penalty(config, jax.tree.map(  # noqa: E731
        lambda a, d: a + t * d, anchor, direction), anchor, f))
    assert at(0.0) == 0.0
    assert 0.0 < at(0.1) < at(0.2) < at(0.4)
    np.testing.assert_allclose(at(0.2), 4 * at(0.1), rtol=1e-4)  # quadratic in the distance
    expected = 0.5 * config.ewc_lambda * config.ewc_gamma * 0.01 * sum(
        float(jnp.sum(f * d * d)) for f, d in zip(jax.tree.leaves(fisher), jax.tree.leaves(direction)))
    np.testing.assert_allclose(at(0.1), expected, rtol=1e-4)
    # Weighted by the Fisher: where the Fisher is zero, moving costs nothing.
    zero = jax.tree.map(jnp.zeros_like, fisher)
    assert at(0.4, zero) == 0.0
    doubled = jax.tree.map(lambda f: 2 * f, fisher)
    np.testing.assert_allclose(at(0.1, doubled), 2 * at(0.1), rtol=1e-5)
    # The distillation loss is the KL plus exactly this penalty, and its gradient pulls back towards the anchor.
    obs = jax.random.normal(jax.random.PRNGKey(8), (5, kb["obs_norm"].mean.shape[0]))
    t_mean, t_log_std = networks.policy_dist(kb, obs)
    moved = jax.tree.map(lambda a, d: a + 0.1 * d, anchor, direction)
    loss, kl = pnc.distill_loss(config, moved, kb, t_mean, t_log_std, obs, jnp.ones(5), anchor, fisher)
    np.testing.assert_allclose(float(loss - kl), at(0.1), rtol=1e-4)
    grad = jax.grad(lambda t: pnc.distill_loss(config, t, kb, t_mean, t_log_std, obs, jnp.ones(5), anchor,
                                               fisher)[0])(moved)
    assert sum(float(jnp.vdot(g, d)) for g, d in zip(jax.tree.leaves(grad), jax.tree.leaves(direction))) > 0


def test_distillation_lowers_the_kl_and_updates_the_online_fisher():
    family, config, kb, active, _ = _pnc_policies()
    config = dataclasses.replace(config, ppo=dataclasses.replace(config.ppo, num_updates=20), ewc_lambda=0.0)
    task = envs.task_at(family, 0)
    fisher0 = jax.tree.map(lambda x: jnp.full(x.shape, 0.5, x.dtype), pnc.trainable(kb))
    run = jax.jit(lambda kb, active: pnc.compress(config, family, kb, active, task, fisher0, pnc.trainable(kb),
                                                  jax.random.PRNGKey(7), 4))
    new_kb, fisher, anchor, kls, bad = run(kb, active)
    kls = np.asarray(kls)
    assert kls[-1] < 0.5 * kls[0], kls
    assert float(bad) == 0.0
    # The anchor is the new knowledge base; F* = γ F*_old + F_k with F_k normalised to a largest entry of 1.
    for a, b in zip(jax.tree.leaves(anchor), jax.tree.leaves(pnc.trainable(new_kb))):
        np.testing.assert_array_equal(a, b)
    new_part = jax.tree.map(lambda f: f - config.ewc_gamma * 0.5, fisher)
    top = max(float(jnp.max(f)) for f in jax.tree.leaves(new_part))
    np.testing.assert_allclose(top, 1.0, rtol=1e-5)
    assert min(float(jnp.min(f)) for f in jax.tree.leaves(new_part)) >= -1e-6


def test_gaussian_kl_is_zero_for_equal_policies_and_positive_otherwise():
    m = jnp.array([[0.3, -0.2]])
    s = jnp.array([-0.5, 0.1])
    assert float(pnc.gaussian_kl(m, s, m, s)[0]) == pytest.approx(0.0, abs=1e-7)
    assert float(pnc.gaussian_kl(m + 0.1, s, m, s)[0]) > 0.0
    # KL(N(0,1) || N(0, e^2)) per dimension: log e - 1/2 + 1/(2 e^2)
    kl = pnc.gaussian_kl(jnp.zeros((1, 1)), jnp.zeros(1), jnp.zeros((1, 1)), jnp.ones(1))
    np.testing.assert_allclose(float(kl[0]), 1.0 - 0.5 + 0.5 * np.exp(-2.0), rtol=1e-6)


@pytest.mark.parametrize("name", ["maml_tl", "pnc"])
def test_learn_task_reports_the_shared_metrics(name):
    """... and, with ``std_mode="reset"`` (PNC carrying its active column over), starts the task at ``init_std``
    whatever std the last task left (tests/test_exploration.py has the other methods and modes)."""
    family = envs.make("point_goal")
    base = methods.default_config(name, family)
    extra = {"reset_active": False} if name == "pnc" else {}
    method = methods.make(name, family, dataclasses.replace(base, ppo=dataclasses.replace(TINY_PPO, std_mode="reset"),
                                                            **extra))
    state = method.init(jax.random.PRNGKey(0))
    narrowed = lambda policy: {**policy, "log_std": jnp.full_like(policy["log_std"], np.log(0.05))}  # noqa: E731
    state = state._replace(params=state.params._replace(policy=narrowed(state.params.policy)))
    if name == "pnc":
        state = state._replace(active=narrowed(state.active))
    state2, metrics = jax.jit(method.learn_task)(state, envs.task_at(family, 0))
    np.testing.assert_allclose(float(metrics.policy_health.std_start), TINY_PPO.init_std, rtol=1e-6)
    assert metrics.per_iteration.valid.shape == (4,)
    assert 1 <= int(metrics.iterations) <= 4 and int(state2.task_index) == 1
    chex.assert_trees_all_equal_shapes_and_dtypes(state2, state)  # a lax.scan over tasks can carry it
    steps = methods.base.env_steps_per_iteration(method)
    assert steps == (2 if name == "maml_tl" else 1) * TINY_PPO.num_trajectories * family.max_steps
    compress = pnc.compress_iterations(method.config, 4) if name == "pnc" else 0  # PNC's compress phase, per task
    assert method.env_steps_per_task == compress * TINY_PPO.num_trajectories * family.max_steps


@pytest.mark.parametrize("field,value", [("inner_learning_rate", 0.0), ("inner_objective", "trpo")])
def test_bad_maml_config_names_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        maml_tl.MAMLTLConfig(**{field: value})


@pytest.mark.parametrize("field,value", [("compress_fraction", 1.0), ("ewc_lambda", -1.0), ("ewc_gamma", 1.5),
                                         ("distill_learning_rate", 0.0)])
def test_bad_pnc_config_names_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        pnc.PNCConfig(**{field: value})


# --- through the runner: CLI, chunks, checkpoints, exact resume, results ---

TINY_RUN = ["--methods", "maml_tl", "pnc", "--num-tasks", "3", "--seeds", "2", "--chunk-tasks", "1", "--budget", "3",
            "--num-trajectories", "2", "--hidden-sizes", "8", "8", "--num-updates", "1", "--minibatch-size", "16",
            "--heldout-iterations", "1", "--heldout-budget", "2", "--backward-tasks", "1"]


@pytest.fixture(scope="module")
def baselines_run(tiny_run):
    return tiny_run(TINY_RUN, "baselines")


def test_baselines_run_end_to_end_with_samples_to_success(baselines_run):
    results = json.loads((baselines_run / "results.json").read_text())
    assert list(results["methods"]) == ["maml_tl", "pnc"]
    for name, factor in (("maml_tl", 2), ("pnc", 1)):
        m = results["methods"][name]
        assert np.asarray(m["iterations_to_success"]).shape == (2, 3)
        assert m["env_steps_per_iteration"] == factor * 2 * 100
        # Samples-to-success: the iterations' batches, plus PNC's compress batch (1 of budget 3) on solved tasks
        assert m["env_steps_per_task"] == (200 if name == "pnc" else 0)
        its, solved = np.asarray(m["iterations_to_success"]), np.asarray(m["solved"])
        expected = its * factor * 200 + solved * m["env_steps_per_task"]
        np.testing.assert_array_equal(m["env_steps_to_success"], expected)
        np.testing.assert_allclose(m["env_steps_to_success_mean"], expected.mean(0))
        assert np.asarray(m["backward_transfer"], dtype=object).shape == (2, 3)
        assert m["nonfinite_iterations"] == 0
    assert "significance" not in results  # no comps in the run: no default baseline
    assert (baselines_run / "plots" / "samples_to_success.png").stat().st_size > 1000


def test_killed_and_resumed_baselines_equal_the_uninterrupted_run(runner, baselines_run, tmp_path, kill_and_resume):
    kill_and_resume(runner, TINY_RUN, tmp_path / "killed", ["maml_tl", "pnc"], baselines_run)
