"""Laws of the shared networks: the Gaussian policy's log-probability, actions and entropy, the observation
normaliser's running statistics, the MLPs' shapes."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats

from jcomps.training import networks


def _params(seed=0, obs_size=3, action_size=2, hidden=(8,), init_std=0.5):
    return networks.init_actor_critic(jax.random.PRNGKey(seed), obs_size, action_size, hidden, init_std)


def test_log_prob_matches_closed_form():
    params = _params()
    obs = jnp.ones((5, 3))
    noise = jax.random.normal(jax.random.PRNGKey(1), (5, 2))
    action, logp = networks.GAUSSIAN.act(params.policy, obs, noise)
    mean, log_std = networks.policy_dist(params.policy, obs)
    std = np.exp(np.asarray(log_std))
    manual = np.sum(-0.5 * ((np.asarray(action) - np.asarray(mean)) / std) ** 2 - np.log(std * np.sqrt(2 * np.pi)),
                    axis=-1)
    chex.assert_trees_all_close(np.asarray(logp), manual, rtol=1e-5)
    assert not params.policy["log_std"].weak_type


def test_log_prob_is_scipys_and_equals_the_log_prob_act_reports():
    rng = np.random.default_rng(0)
    mean = rng.normal(size=(4, 3)).astype(np.float32)
    log_std = rng.normal(0.0, 0.5, size=3).astype(np.float32)
    action = rng.normal(size=(4, 3)).astype(np.float32)
    want = stats.norm.logpdf(action, mean, np.exp(log_std)).sum(-1)
    np.testing.assert_allclose(networks.gaussian_log_prob(mean, log_std, action), want, rtol=1e-5)
    # act's log-probability (from the noise) is the policy's log-probability of the action it takes
    params = _params(hidden=(8, 4))
    obs = jnp.asarray(rng.normal(size=(6, 3)), jnp.float32)
    action, log_prob = networks.GAUSSIAN.act(params.policy, obs, jnp.asarray(rng.normal(size=(6, 2)), jnp.float32))
    np.testing.assert_allclose(log_prob, networks.GAUSSIAN.log_prob(params.policy, obs, action), rtol=1e-5)


def test_act_with_zero_noise_gives_the_mean_at_its_density_peak():
    params = _params(hidden=(8, 4))
    obs = jax.random.normal(jax.random.PRNGKey(2), (2, 5, 3))
    action, log_prob = networks.GAUSSIAN.act(params.policy, obs, jnp.zeros((2, 5, 2)))
    mean, log_std = networks.GAUSSIAN.dist(params.policy, obs)
    chex.assert_trees_all_equal(action, mean)
    chex.assert_shape([action, log_prob], [(2, 5, 2), (2, 5)])
    np.testing.assert_allclose(log_prob, -np.sum(np.asarray(log_std) + 0.5 * np.log(2 * np.pi)), rtol=1e-6)


def test_entropy_is_the_diagonal_gaussians():
    log_std = np.array([-1.0, 0.0, 0.7], np.float32)
    want = sum(stats.norm(0.0, s).entropy() for s in np.exp(log_std))
    np.testing.assert_allclose(networks.gaussian_entropy(log_std), want, rtol=1e-6)
    np.testing.assert_allclose(networks.gaussian_entropy(log_std), np.sum(0.5 * np.log(2 * np.pi * np.e) + log_std),
                               rtol=1e-6)


def test_obs_norm_merge_equals_statistics_of_all_data():
    # Law: merging batches one by one gives the mean and (population) variance of all the data at once, and
    # masked-out entries count for nothing.
    rng = np.random.default_rng(0)
    batches = [rng.normal(3.0, 2.0, size=(7, 4, 3)).astype(np.float32) for _ in range(3)]
    masks = [(rng.random((7, 4)) < 0.7).astype(np.float32) for _ in range(3)]
    norm = networks.obs_norm_init(3)
    for x, m in zip(batches, masks):
        norm = networks.obs_norm_update(norm, jnp.asarray(x), jnp.asarray(m))
    kept = np.concatenate([x[m > 0] for x, m in zip(batches, masks)])
    np.testing.assert_allclose(np.asarray(norm.mean), kept.mean(0), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(np.asarray(norm.var), kept.var(0), rtol=1e-4, atol=1e-5)
    assert float(norm.count) == len(kept)
    # An empty batch changes nothing.
    same = networks.obs_norm_update(norm, jnp.asarray(batches[0]), jnp.zeros((7, 4), jnp.float32))
    chex.assert_trees_all_equal(same, norm)


def test_normalised_observations_and_no_gradient_into_the_statistics():
    params = _params()
    obs = jnp.asarray(np.random.default_rng(1).normal(5.0, 3.0, size=(50, 3)), jnp.float32)
    norm = networks.obs_norm_update(params.policy["obs_norm"], obs, jnp.ones((50,), jnp.float32))
    policy = {**params.policy, "obs_norm": norm}
    z = networks.normalize_obs(policy, obs)
    np.testing.assert_allclose(np.asarray(z.mean(0)), 0.0, atol=1e-5)
    np.testing.assert_allclose(np.asarray(z.std(0)), 1.0, atol=1e-4)
    assert float(jnp.max(jnp.abs(networks.normalize_obs(policy, obs * 1e6)))) == networks.OBS_CLIP
    grads = jax.grad(lambda p: jnp.sum(networks.GAUSSIAN.log_prob(p, obs, jnp.ones((50, 2)))))(policy)
    chex.assert_trees_all_equal(grads["obs_norm"], jax.tree.map(jnp.zeros_like, norm))
    # A fresh normaliser is the identity.
    np.testing.assert_array_equal(networks.normalize_obs(params.policy, obs / 10), obs / 10)


def test_init_shapes_and_initial_std():
    params = _params(obs_size=5, action_size=3, hidden=(16, 8), init_std=0.3)
    chex.assert_shape([layer["w"] for layer in params.policy["mean"]], [(5, 16), (16, 8), (8, 3)])
    chex.assert_shape([layer["w"] for layer in params.value], [(5, 16), (16, 8), (8, 1)])
    np.testing.assert_allclose(np.exp(params.policy["log_std"]), np.full(3, 0.3), rtol=1e-6)
    chex.assert_trees_all_equal(params.policy["obs_norm"], networks.obs_norm_init(5))
    obs = jax.random.normal(jax.random.PRNGKey(1), (4, 7, 5))
    chex.assert_shape(networks.value_of(params, obs), (4, 7))
    # Leading axes are batch axes: the MLP on [4, 7, n] is the MLP on each row.
    rows = networks.mlp_apply(params.policy["mean"], obs.reshape(28, 5)).reshape(4, 7, 3)
    np.testing.assert_allclose(networks.mlp_apply(params.policy["mean"], obs), rows, rtol=1e-6, atol=1e-6)
