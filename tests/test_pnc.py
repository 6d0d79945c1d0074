"""Progress & Compress: the knowledge base's observation statistics (issue 28). They pool every compressed task
with equal weight, and re-expressing the KB in new statistics keeps its function on the states of earlier tasks;
on MetaWorld, after Push and then Hammer, the KB sees both tasks' observations inside the clip."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jcomps import envs
from jcomps.envs import host_acting
from jcomps.methods import pnc
from jcomps.training import acting, networks, ppo

TINY_PPO = ppo.PPOConfig(num_trajectories=2, num_updates=1, minibatch_size=16, hidden_sizes=(8, 8), budget=2)


def _norm_of(x):
    return pnc.task_statistics(jnp.asarray(x), jnp.ones(x.shape[:-1]))


def test_pooled_statistics_weigh_every_task_equally():
    rng = np.random.default_rng(0)
    tasks = [rng.normal(loc, scale, (n, 3)).astype(np.float32)
             for loc, scale, n in [(0.0, 1.0, 40), (5.0, 0.1, 400), (-2.0, 3.0, 7)]]
    pooled = networks.obs_norm_init(3)
    for i, x in enumerate(tasks):
        pooled = pnc.pool_statistics(pooled, _norm_of(x), 10.0)
        if i == 0:  # an empty pool becomes the first task's statistics
            np.testing.assert_allclose(pooled.mean, x.mean(0), rtol=1e-5)
            np.testing.assert_allclose(pooled.var, x.var(0), rtol=1e-4)
    # The equal-weight mixture of the three tasks (not the 447 samples pooled by count).
    means, variances = np.stack([x.mean(0) for x in tasks]), np.stack([x.var(0) for x in tasks])
    mean = means.mean(0)
    np.testing.assert_allclose(pooled.mean, mean, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(pooled.var, (variances + (means - mean) ** 2).mean(0), rtol=1e-4)
    assert float(pooled.count) == 30.0
    by_count = np.concatenate(tasks).mean(0)
    assert np.all(np.abs(by_count - mean) > 0.5)  # what a count-weighted pool would have given instead


def _kb_with_statistics(seed, norm):
    kb = networks.init_actor_critic(jax.random.PRNGKey(seed), 4, 2, (16, 8), 0.5).policy
    layers = [{"w": layer["w"] + 0.5 * jax.random.normal(jax.random.PRNGKey(seed + i + 1), layer["w"].shape),
               "b": 0.3 * jax.random.normal(jax.random.PRNGKey(seed + i + 7), layer["b"].shape)}
              for i, layer in enumerate(kb["mean"])]
    return {**kb, "mean": layers, "obs_norm": norm}


def test_renormalising_keeps_the_kbs_function_on_the_old_states():
    rng = np.random.default_rng(1)
    # Old states: dimension 2 constant (its std at the floor), the others varying; new states move all four.
    old = rng.normal([0.5, -1.0, 0.0, 2.0], [0.3, 1.0, 0.0, 0.05], (200, 4)).astype(np.float32)
    new = rng.normal([1.0, 0.0, 0.24, 2.5], [0.5, 2.0, 0.1, 0.5], (200, 4)).astype(np.float32)
    old_norm = pnc.pool_statistics(networks.obs_norm_init(4), _norm_of(old), 100.0)
    new_norm = pnc.pool_statistics(old_norm, _norm_of(new), 100.0)
    kb = _kb_with_statistics(0, old_norm)
    anchor = pnc.trainable(_kb_with_statistics(20, old_norm))
    fisher = jax.tree.map(lambda x: jnp.full(x.shape, 2.0), anchor)
    kb2, anchor2, fisher2 = pnc.renormalise(kb, anchor, fisher, new_norm)
    assert kb2["obs_norm"] is new_norm
    np.testing.assert_allclose(networks.policy_dist(kb2, old)[0], networks.policy_dist(kb, old)[0], rtol=1e-4,
                               atol=1e-5)
    # Only the statistics changed, the function on the old states would move: the re-expression is what keeps it.
    swapped = networks.policy_dist({**kb, "obs_norm": new_norm}, old)[0]
    assert float(jnp.max(jnp.abs(swapped - networks.policy_dist(kb, old)[0]))) > 0.05
    # The anchor is the same function before and after; only the first layer changes.
    np.testing.assert_allclose(networks.policy_dist({**kb2, **anchor2}, old)[0],
                               networks.policy_dist({**kb, **anchor}, old)[0], rtol=1e-4, atol=1e-5)
    for a, b in zip(jax.tree.leaves(kb["mean"][1:]), jax.tree.leaves(kb2["mean"][1:])):
        np.testing.assert_array_equal(a, b)
    # The floored dimension's row is not scaled by s'/1e-3; the others are by s'/s, their Fisher by 1/r².
    old_std, new_std = np.sqrt(old_norm.var), np.sqrt(new_norm.var)
    assert old_std[2] <= networks.OBS_STD_MIN < new_std[2]
    ratio = np.where(old_std > networks.OBS_STD_MIN, new_std / np.maximum(old_std, networks.OBS_STD_MIN), 1.0)
    np.testing.assert_allclose(kb2["mean"][0]["w"], kb["mean"][0]["w"] * ratio[:, None], rtol=1e-5)
    np.testing.assert_array_equal(kb2["mean"][0]["w"][2], kb["mean"][0]["w"][2])
    np.testing.assert_allclose(fisher2["mean"][0]["w"], np.broadcast_to(2.0 / ratio[:, None] ** 2, (4, 16)), rtol=1e-5)
    np.testing.assert_array_equal(fisher2["mean"][0]["b"], fisher["mean"][0]["b"])
    # A fresh knowledge base (count 0, the untrained network) just takes the statistics.
    fresh = _kb_with_statistics(0, networks.obs_norm_init(4))
    fresh2, _, fisher3 = pnc.renormalise(fresh, pnc.trainable(fresh), fisher, old_norm)
    for a, b in zip(jax.tree.leaves(fresh["mean"]), jax.tree.leaves(fresh2["mean"])):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(fisher3["mean"][0]["w"], fisher["mean"][0]["w"])


def test_a_column_without_laterals_is_its_own_mlp_policy():
    """With every adaptor's scale α at 0 the active column (``COLUMN``) acts as the plain Gaussian policy of its own
    layers, whatever its knowledge base; with α > 0 the knowledge base shapes its actions."""
    family = envs.make("point_goal")
    config = pnc.PNCConfig(ppo=TINY_PPO)
    kb = ppo.init_params(config.ppo, family, jax.random.PRNGKey(0)).policy
    active, _ = pnc.init_active(config, family, jax.random.PRNGKey(1), kb["obs_norm"])
    silent = {**active, "adaptors": [{**a, "alpha": jnp.zeros_like(a["alpha"])} for a in active["adaptors"]]}
    obs = jax.random.normal(jax.random.PRNGKey(2), (3, 5, family.obs_size))
    noise = jax.random.normal(jax.random.PRNGKey(3), (3, 5, family.action_size))
    column, plain = pnc.COLUMN.act(pnc.with_kb(silent, kb), obs, noise), networks.GAUSSIAN.act(silent, obs, noise)
    np.testing.assert_allclose(column[0], plain[0], rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(column[1], plain[1])
    lateral = pnc.COLUMN.dist(pnc.with_kb(active, kb), obs)[0]
    assert float(jnp.max(jnp.abs(lateral - networks.GAUSSIAN.dist(active, obs)[0]))) > 1e-4
    assert pnc.COLUMN.host_kind in host_acting.TWINS


def test_a_bad_kb_statistics_names_the_field():
    with pytest.raises(ValueError, match="kb_statistics"):
        pnc.PNCConfig(kb_statistics="running")


def _raw_z(norm, obs):
    """Observations standardised by ``norm`` before the clip."""
    return np.abs((np.asarray(obs) - norm.mean) / np.maximum(np.sqrt(norm.var), networks.OBS_STD_MIN))


def test_after_push_then_hammer_the_knowledge_base_sees_both_inside_the_clip():
    """P-0 then H-2 on MetaWorld, the method's own learn_task (1 progress and 1 compress iteration of 2 episodes
    each): Hammer's second-object dimensions (11-14, 29-32: 0 in every Push state) are inside the clip for the
    KB. The statistics of Push alone (what the KB kept before issue 28) put them hundreds of stds out."""
    family = envs.make("metaworld")
    method = pnc.make(family, pnc.PNCConfig(ppo=TINY_PPO))
    push, hammer = (jax.tree.map(lambda x, i=i: x[i], family.tasks([0.0, 202.0])) for i in range(2))
    state = method.init(jax.random.PRNGKey(0))
    learn = jax.jit(method.learn_task)
    state, _ = learn(state, push)
    after_push = state.params.policy["obs_norm"]
    state, _ = learn(state, hammer)
    kb = state.params.policy
    assert float(kb["obs_norm"].count) == 2 * TINY_PPO.num_trajectories * family.max_steps  # two tasks pooled
    roll = jax.jit(lambda task: acting.rollout(family, kb, task, jax.random.PRNGKey(5), 2).obs)
    obs = {"push": roll(push), "hammer": roll(hammer)}
    second_object = np.r_[11:15, 29:33]
    for name, x in obs.items():
        z = _raw_z(kb["obs_norm"], x)
        assert z.max() < networks.OBS_CLIP, (name, z.max(axis=(0, 1)))
        # Constant within each task: the two-task pool puts them one std either side of the pooled mean.
        assert z[..., second_object].max() < 1.5, (name, z[..., second_object].max(axis=(0, 1)))
    assert np.all(np.asarray(obs["push"])[..., second_object] == 0.0)
    assert _raw_z(after_push, obs["hammer"])[..., second_object].min() > 100.0
