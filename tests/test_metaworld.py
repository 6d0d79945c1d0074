"""The MetaWorld family: the paper's task list and rules on the real ``metaworld`` package, pure host stepping
that equals MetaWorld's own, reproducible rollouts, and the runner end to end (a handful of steps each)."""

from __future__ import annotations

import dataclasses
import json
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jcomps import envs, methods
from jcomps.envs import host_acting
from jcomps.envs import metaworld as mw
from jcomps.envs import metaworld_host as host
from jcomps.training import acting, networks, ppo


@pytest.fixture(scope="module")
def family():
    return envs.make("metaworld")


def test_the_sequence_is_the_papers(family):
    labels = [mw.label(v) for v in envs.sequence_values(family, "non-stationary")]
    assert len(labels) == 39
    assert labels[:6] == ["P-0", "B-1", "H-2", "P-3", "B-4", "H-5"]
    # The paper's "P-1P", "B-1B", "H-2H" are typos for P-15, B-16, H-29 (SPEC).
    assert labels[15] == "P-15" and labels[16] == "B-16" and labels[29] == "H-29"
    assert labels[-1] == "H-38"
    assert [host.ENV_NAMES[i] for i in range(3)] == ["push-wall-v3", "button-press-wall-v3", "hammer-v3"]
    stationary = envs.sequence_values(family, "stationary", seed=3)
    assert sorted(stationary.tolist()) == sorted(envs.sequence_values(family).tolist())
    assert stationary.tolist() != envs.sequence_values(family).tolist()


def test_held_out_goal_indices_are_never_in_the_sequence(family):
    seen = {(int(v) // 100, int(v) % 100) for v in family.task_values}
    held = [(int(v) // 100, int(v) % 100) for v in family.held_out_values]
    assert len(held) == 9 and {e for e, _ in held} == {0, 1, 2}
    assert not {k for _, k in held} & {k for _, k in seen}


def test_the_family_has_the_papers_rules(family):
    assert (family.max_steps, family.success_threshold, family.default_budget) == (150, 0.2, 500)
    assert (family.obs_size, family.action_size) == (39, 4)
    config = methods.default_config("comps", family)
    assert config.meta.inner_learning_rate == 0.0025
    assert methods.default_config("comps", "cheetah_vel").meta.inner_learning_rate == 0.005


def test_success_rate_counts_trajectories_with_a_success(family):
    success = np.zeros((150, 5), np.float32)
    success[3, 0] = 1.0            # one step
    success[100:, 1] = 1.0         # many steps still count once
    success[149, 4] = 1.0          # the last step counts
    assert float(family.success_rate(jnp.asarray(success))) == pytest.approx(3 / 5)
    assert float(family.success_rate(jnp.zeros((150, 4)))) == 0.0


@pytest.mark.parametrize("bad", [150.0, 1.5, -1.0, 300.0])
def test_task_codes_that_name_no_task_are_refused(family, bad):
    with pytest.raises(ValueError, match="task code"):
        family.tasks([bad])


def test_host_steps_equal_metaworlds_own_steps():
    """Our pure step (state in, state out) equals stepping MetaWorld's env object, bit for bit, with either reward
    function (host environments 3-5: the v1 reward, the family ``metaworld_v1``)."""
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    rng = np.random.default_rng(0)
    for env, k in [(0, 3), (2, 5), (5, 5)]:
        version = host.REWARD_VERSIONS[env // 3]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ref = ALL_V3_ENVIRONMENTS[host.ENV_NAMES[env % 3]](reward_function_version=version)
            ref.set_task(host.variants(env % 3)[k])
            ref.max_path_length = 150
            obs_ref, _ = ref.reset()
        state, obs = host.reset([env], [k])
        np.testing.assert_array_equal(obs[0], obs_ref)
        for _ in range(6):
            action = rng.uniform(-1, 1, (1, 4)).astype(np.float32)
            obs_ref, reward_ref, terminated, _, info = ref.step(action[0])
            state, obs, reward, success = host.step([env], [k], state, action)
            np.testing.assert_array_equal(obs[0], obs_ref)
            assert reward[0] == reward_ref and success[0] == info["success"] and not terminated
    # The two rewards differ on the same state and action; the rest of the step is the same.
    state, _ = host.reset([2, 5], [5, 5])
    _, obs, reward, success = host.step([2, 5], [5, 5], state, np.full((2, 4), 0.5, np.float32))
    np.testing.assert_array_equal(obs[0], obs[1])
    assert reward[0] != reward[1] and success[0] == success[1]


def test_the_v1_reward_family_names_the_same_tasks():
    v1 = envs.make("metaworld_v1")
    assert v1.name == "metaworld_v1" and v1.task_values == envs.make("metaworld").task_values
    task = v1.tasks(v1.parse_values(["P-3", "H-11"]))
    np.testing.assert_array_equal(task.env, [3, 5])  # host environments with the v1 reward
    np.testing.assert_array_equal(task.variant, [3, 11])
    v1_config, v2_config = (methods.default_config("ppo_tl", f) for f in ("metaworld_v1", "metaworld"))
    assert (v1_config.ppo.reward_scale, v2_config.ppo.reward_scale) == (0.001, 0.1)  # v1's returns are 10^2-10^4 larger
    assert dataclasses.replace(v1_config, ppo=dataclasses.replace(v1_config.ppo, reward_scale=0.1)) == v2_config
    # every reward scale takes the same factor, PEARL's own too
    v1_pearl, v2_pearl = (methods.default_config("pearl", f) for f in ("metaworld_v1", "metaworld"))
    assert v1_pearl.reward_scale == pytest.approx(0.01 * v2_pearl.reward_scale)


def test_a_variant_starts_from_the_same_state_every_reset_and_variants_differ():
    a, obs_a = host.reset([0, 0], [3, 3])
    np.testing.assert_array_equal(a[0], a[1])
    np.testing.assert_array_equal(obs_a[0], obs_a[1])
    variant = host._get(0, 3).env
    variant.reset()
    goal = variant._target_pos.copy()
    variant.reset()
    np.testing.assert_array_equal(variant._target_pos, goal)
    assert not np.array_equal(host._get(0, 6).env._target_pos, goal)
    # The goal is hidden (ML1's tasks): the last three observation entries are zero.
    np.testing.assert_array_equal(obs_a[0][-3:], 0.0)


def test_a_pool_of_workers_steps_like_one_process():
    rng = np.random.default_rng(1)
    env, variant = np.array([0, 1, 2, 0]), np.array([0, 1, 2, 3])
    state, _ = host.reset(env, variant)
    pool = host.Pool(workers=2)
    try:
        s1, s2 = state, state
        for _ in range(3):
            action = rng.uniform(-1, 1, (4, 4)).astype(np.float32)
            a, b = host.step(env, variant, s1, action), pool.step(env, variant, s2, action)
            for x, y in zip(a, b):
                np.testing.assert_array_equal(x, y)
            s1, s2 = a[0], b[0]
    finally:
        pool.close()
    with pytest.raises(ValueError, match="workers"):
        host.Pool(workers=0)


def test_a_pool_of_workers_rolls_out_like_one_process():
    """Whole episodes (two policies, three environments) split over two processes equal one process's, bit for bit."""
    rng = np.random.default_rng(2)
    policies = [host_acting.plain(networks.init_actor_critic(jax.random.PRNGKey(i), 39, 4, (8,), 0.5).policy)
                for i in range(2)]
    group, episode = np.array([0, 0, 1, 1, 1]), np.array([0, 1, 0, 1, 2])
    env, variant = np.array([0, 1, 2, 0, 1]), np.array([0, 1, 2, 3, 4])
    noise = rng.standard_normal((5, 4, 4)).astype(np.float32)
    one = host.rollout("gaussian", policies, group, episode, env, variant, noise)
    pool = host.Pool(workers=2)
    try:
        two = pool.rollout("gaussian", policies, group, episode, env, variant, noise)
    finally:
        pool.close()
    assert [x.shape for x in one] == [(5, 5, 39), (5, 4, 4), (5, 4), (5, 4), (5, 4)]
    for x, y in zip(one, two):
        np.testing.assert_array_equal(x, y)
    with pytest.raises(ValueError, match="no host twin of kind 'nope'"):
        host.rollout("nope", policies, group, episode, env, variant, noise)


def _perturbed(tree, seed):
    """Every leaf of ``tree`` moved by noise, so zero biases and identity normalisers are exercised too."""
    leaves, treedef = jax.tree.flatten(tree)
    keys = jax.random.split(jax.random.PRNGKey(seed), len(leaves))
    out = jax.tree.unflatten(treedef, [x + 0.3 * jax.random.normal(k, x.shape, x.dtype) if x.ndim else x + 5.0
                                       for x, k in zip(leaves, keys)])
    if isinstance(out, dict) and "obs_norm" in out:  # a variance stays positive
        out["obs_norm"] = out["obs_norm"]._replace(var=jnp.abs(out["obs_norm"].var) + 1e-4)
    return out


def _policies_with_twins():
    """(name, actor, policy) for every actor that has a NumPy twin: the Gaussian MLP, Progress & Compress's active
    column (laterals from a knowledge base) and PEARL's tanh-Gaussian with a per-episode z."""
    from jcomps.methods import pearl, pnc

    plain_policy = _perturbed(networks.init_actor_critic(jax.random.PRNGKey(0), 39, 4, (16, 8), 0.5).policy, 1)
    kb = _perturbed(networks.init_actor_critic(jax.random.PRNGKey(2), 39, 4, (16, 8), 0.5).policy, 3)
    column = {**_perturbed({**networks.init_actor_critic(jax.random.PRNGKey(4), 39, 4, (16, 8), 0.5).policy,
                            "adaptors": pnc.adaptors_init(jax.random.PRNGKey(5), (39, 16, 8, 4))}, 6),
              "kb": kb}
    config = pearl.PEARLConfig(hidden_sizes=(16, 8))
    fam = envs.make("metaworld")
    nets = pearl.make_networks(config, fam)
    net = _perturbed(nets.sac.policy_network.init(jax.random.PRNGKey(7)), 8)
    z = jax.random.normal(jax.random.PRNGKey(9), (6, config.latent_size))
    return [("gaussian", acting.GAUSSIAN, plain_policy), ("column", acting.actor_of(pnc.COLUMN), column),
            ("tanh_gaussian", pearl.make_actor(nets), {"net": net, "z": z})]


def test_numpy_twins_act_like_the_jax_policies():
    # The twins' copies of the normaliser's constants (host_acting imports no JAX, so it cannot import them).
    assert (host_acting.OBS_CLIP, host_acting.OBS_STD_MIN) == (np.float32(networks.OBS_CLIP),
                                                               np.float32(networks.OBS_STD_MIN))
    obs = np.asarray(30.0 * jax.random.normal(jax.random.PRNGKey(10), (6, 39)))  # some beyond the clip
    noise = np.asarray(jax.random.normal(jax.random.PRNGKey(11), (6, 4)))
    for name, actor, policy in _policies_with_twins():
        want_action, want_log_prob = jax.jit(actor.act)(policy, obs, noise)
        plain = host_acting.plain(jax.tree.map(np.asarray, policy))
        action, log_prob = host_acting.act(actor.host_kind, plain, obs, noise, np.arange(6))
        assert action.dtype == log_prob.dtype == np.float32
        np.testing.assert_allclose(action, want_action, rtol=1e-5, atol=1e-5, err_msg=name)
        np.testing.assert_allclose(log_prob, want_log_prob, rtol=1e-4, atol=1e-4, err_msg=name)  # float32 sums
        # Row by row: an episode's action does not depend on which episodes share its batch.
        rows = np.array([4, 1])
        part = host_acting.act(actor.host_kind, plain, obs[rows], noise[rows], rows)
        np.testing.assert_array_equal(part[0], action[rows], err_msg=name)
        np.testing.assert_array_equal(part[1], log_prob[rows], err_msg=name)


def test_host_rollouts_equal_rollouts_stepped_through_the_family(family):
    """The host rollout (the policy's NumPy twin, two seeds under vmap) takes the steps that stepping through
    ``family.step`` with the JAX policy takes, to float32 rounding; an actor without a twin steps."""
    config = methods.default_config("ppo_tl", "metaworld").ppo
    policies = jax.vmap(lambda k: ppo.init_params(config, family, k).policy)(jax.random.split(jax.random.PRNGKey(0)))
    task = envs.task_at(family, 2)
    keys = jax.random.split(jax.random.PRNGKey(3))

    def run(actor):
        return jax.jit(jax.vmap(lambda p, k: acting.rollout(family, p, task, k, 2, actor)))(policies, keys)

    fast, stepped = run(acting.GAUSSIAN), run(acting.Actor(acting.GAUSSIAN.act))
    assert fast.obs.shape == stepped.obs.shape == (2, 150, 2, 39)
    for field in ("obs", "action", "log_prob", "reward", "success"):
        np.testing.assert_allclose(getattr(fast, field)[:, :40], getattr(stepped, field)[:, :40], rtol=1e-4,
                                   atol=1e-4, err_msg=field)
    np.testing.assert_array_equal(fast.done, 0.0)
    np.testing.assert_array_equal(fast.valid, 1.0)
    assert not np.array_equal(fast.obs[0], fast.obs[1])


def test_a_rollout_marked_inactive_is_not_run_and_the_others_are_unchanged(family):
    """Inside ``acting.only_if`` (the RL loop's condition under vmap) the host skips the inactive members'
    episodes (zeros come back) and runs the active ones exactly as without it."""
    config = methods.default_config("ppo_tl", "metaworld").ppo
    policies = jax.vmap(lambda k: ppo.init_params(config, family, k).policy)(jax.random.split(jax.random.PRNGKey(0)))
    task = envs.task_at(family, 1)
    keys = jax.random.split(jax.random.PRNGKey(3))

    def rollout(p, k, active):
        with acting.only_if(active):
            return acting.rollout(family, p, task, k, 2)

    both = jax.jit(jax.vmap(lambda p, k: acting.rollout(family, p, task, k, 2)))(policies, keys)
    first = jax.jit(jax.vmap(rollout))(policies, keys, jnp.array([True, False]))
    for field in ("obs", "action", "log_prob", "reward", "success", "last_obs"):
        np.testing.assert_array_equal(getattr(first, field)[0], getattr(both, field)[0], err_msg=field)
        np.testing.assert_array_equal(getattr(first, field)[1], 0.0, err_msg=field)
    assert np.all(np.abs(both.obs[1]).sum(-1) > 0)  # a run episode has no all-zero observation
    none = jax.jit(jax.vmap(rollout))(policies, keys, jnp.array([False, False]))
    np.testing.assert_array_equal(none.obs, 0.0)

    def nested(p, k, outer, inner):  # nested contexts combine: a member runs only where both hold
        with acting.only_if(outer):
            with acting.only_if(inner):
                return acting.rollout(family, p, task, k, 2)

    nested_fn = jax.jit(jax.vmap(nested))
    same = nested_fn(policies, keys, jnp.array([True, True]), jnp.array([True, False]))
    np.testing.assert_array_equal(same.obs, first.obs)
    crossed = nested_fn(policies, keys, jnp.array([True, False]), jnp.array([False, True]))
    np.testing.assert_array_equal(crossed.obs, 0.0)


def test_every_twin_rolls_out_like_its_jax_act(family):
    """Each actor with a NumPy twin (PEARL's with a per-episode z) takes, in a host rollout, the steps its JAX act
    takes through ``family.step``, to float32 rounding (the first 10 steps)."""
    task = envs.task_at(family, 0)
    for name, actor, policy in _policies_with_twins():
        if "z" in policy:
            policy = {**policy, "z": policy["z"][:2]}

        fast, stepped = (jax.jit(lambda k, a=a: acting.rollout(family, policy, task, k, 2, a))(jax.random.PRNGKey(1))
                         for a in (actor, acting.Actor(actor.act)))
        for field in ("obs", "action", "log_prob", "reward"):
            np.testing.assert_allclose(getattr(fast, field)[:10], getattr(stepped, field)[:10], rtol=1e-3,
                                       atol=1e-3, err_msg=f"{name}: {field}")


@pytest.fixture(scope="module")
def rollout_fn(family):
    config = methods.default_config("ppo_tl", "metaworld").ppo
    params = ppo.init_params(config, family, jax.random.PRNGKey(0))
    task = envs.task_at(family, 1)
    return jax.jit(lambda rng: acting.rollout(family, params.policy, task, rng, 2))


def test_an_episode_is_truncated_at_150_steps_never_terminated(rollout_fn):
    traj = rollout_fn(jax.random.PRNGKey(1))
    assert traj.obs.shape == (150, 2, 39)
    assert float(jnp.sum(traj.done)) == 0.0 and float(jnp.min(traj.valid)) == 1.0
    assert traj.last_obs.shape == (2, 39)


def test_rollouts_reproduce_from_their_key(rollout_fn):
    a, b, c = (rollout_fn(jax.random.PRNGKey(k)) for k in (1, 1, 2))
    np.testing.assert_array_equal(a.obs, b.obs)
    np.testing.assert_array_equal(a.reward, b.reward)
    assert not np.array_equal(a.obs, c.obs)


TINY_RUN = ["--family", "metaworld", "--methods", "comps", "--num-tasks", "2", "--seeds", "2",
            "--chunk-tasks", "1", "--budget", "2", "--num-trajectories", "2", "--hidden-sizes", "8", "8",
            "--num-updates", "2", "--minibatch-size", "8", "--heldout-iterations", "0", "--heldout-budget", "0",
            "--backward-tasks", "1", "--set", "comps.meta.num_meta_steps=1", "--set", "comps.meta.num_outer_steps=1",
            "--set", "comps.max_tasks=2", "--set", "comps.num_offpolicy=2", "--set", "comps.meta.inner_trajectories=2",
            "--set", "comps.meta.skilled_trajectories=2"]


@pytest.fixture(scope="module")
def metaworld_run(tiny_run):
    return tiny_run(TINY_RUN, "metaworld")


def test_the_runner_runs_metaworld_end_to_end(metaworld_run):
    results = json.loads((metaworld_run / "results.json").read_text())
    m = results["methods"]["comps"]
    assert np.asarray(m["iterations_to_success"]).shape == (2, 2)
    assert m["env_steps_per_iteration"] == 2 * 150
    run = json.loads((metaworld_run / "run.json").read_text())
    assert run["methods"]["comps"]["meta"]["inner_learning_rate"] == 0.0025


def test_a_killed_and_resumed_metaworld_run_equals_the_uninterrupted_one(runner, metaworld_run, tmp_path,
                                                                        kill_and_resume):
    kill_and_resume(runner, TINY_RUN, tmp_path / "killed", ["comps"], metaworld_run)


def test_a_metaworld_run_is_the_same_whatever_the_number_of_workers(runner, metaworld_run, tmp_path, monkeypatch):
    """The tiny run again with another number of stepping processes gives the same raw results, array for array."""
    workers = 1 if host.default_workers() != 1 else 2
    mw.pool().close()
    mw.pool.cache_clear()
    monkeypatch.setenv("JCOMPS_METAWORLD_WORKERS", str(workers))
    try:
        runner.main(TINY_RUN + ["--out", str(tmp_path / "other")])
        assert mw.pool().workers == workers
    finally:
        mw.pool().close()
        mw.pool.cache_clear()  # the next use starts a pool of the default size
    with np.load(metaworld_run / "raw" / "comps.npz") as fa, np.load(tmp_path / "other" / "raw" / "comps.npz") as fb:
        assert fa.files == fb.files
        for key in fa.files:
            if key != "seconds":
                np.testing.assert_array_equal(fa[key], fb[key], err_msg=key)
