"""Networks: a Gaussian MLP policy with a state-independent log-std, and an MLP value function.

Parameters are plain pytrees (nested dicts of arrays) so they can be differentiated through, stacked over
seeds and tasks, and checkpointed without any object state.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp

LOG_2PI = math.log(2.0 * math.pi)


def mlp_init(rng: jax.Array, sizes: Sequence[int], final_scale: float = 1.0) -> list[dict]:
    """Layers ``sizes[0] -> ... -> sizes[-1]``: orthogonal(√2) hidden weights, ``final_scale`` last, zero biases."""
    layers = []
    keys = jax.random.split(rng, len(sizes) - 1)
    for i, (key, n_in, n_out) in enumerate(zip(keys, sizes[:-1], sizes[1:])):
        scale = final_scale if i == len(sizes) - 2 else math.sqrt(2.0)
        w = jax.nn.initializers.orthogonal(scale)(key, (n_in, n_out), jnp.float32)
        layers.append({"w": w, "b": jnp.zeros((n_out,), jnp.float32)})
    return layers


def mlp_features(layers: list[dict], x: jax.Array) -> jax.Array:
    """The tanh layers of an MLP (all but the last) over the last axis of ``x``.

    Leading axes are flattened into one before the matrix products and restored after: XLA's CPU backend runs
    ``[T, B, n] @ [n, k]`` up to 3x slower than the same product on ``[T·B, n]`` (measured on the policy MLP).
    """
    lead = x.shape[:-1]
    x = x.reshape((-1, x.shape[-1]))
    for layer in layers:
        x = jnp.tanh(x @ layer["w"] + layer["b"])
    return x.reshape(lead + x.shape[-1:])


def mlp_apply(layers: list[dict], x: jax.Array) -> jax.Array:
    """tanh MLP over the last axis of ``x``; the last layer is linear."""
    h = mlp_features(layers[:-1], x)
    lead = h.shape[:-1]
    out = h.reshape((-1, h.shape[-1])) @ layers[-1]["w"] + layers[-1]["b"]
    return out.reshape(lead + out.shape[-1:])


OBS_CLIP = 10.0
"""Normalised observations are clipped to [-OBS_CLIP, OBS_CLIP] (a guard against rare outliers)."""
OBS_STD_MIN = 1e-3
"""Floor on the running standard deviation (a constant observation component stays finite)."""


class ObsNorm(NamedTuple):
    """Running observation statistics (Welford/Chan merge): ``mean`` and ``var`` f32[obs_size], ``count`` f32[].

    With ``count == 0`` (fresh) the normaliser is the identity (mean 0, variance 1).
    """

    mean: jax.Array
    var: jax.Array
    count: jax.Array


def obs_norm_init(obs_size: int) -> ObsNorm:
    """The identity normaliser."""
    return ObsNorm(jnp.zeros((obs_size,), jnp.float32), jnp.ones((obs_size,), jnp.float32), jnp.float32(0.0))


def obs_norm_update(norm: ObsNorm, obs: jax.Array, mask: jax.Array) -> ObsNorm:
    """Merges the observations ``obs`` f32[..., obs_size] where ``mask`` f32[...] is 1 into ``norm``.

    Exact for any split of the data into batches (the parallel-variance merge of Chan et al.).
    """
    w = mask[..., None].astype(jnp.float32)
    n = jnp.sum(mask.astype(jnp.float32))
    axes = tuple(range(obs.ndim - 1))
    batch_mean = jnp.sum(obs * w, axis=axes) / jnp.maximum(n, 1.0)
    batch_var = jnp.sum(w * jnp.square(obs - batch_mean), axis=axes) / jnp.maximum(n, 1.0)
    total = norm.count + n
    delta = batch_mean - norm.mean
    frac = n / jnp.maximum(total, 1.0)
    mean = norm.mean + delta * frac
    var = (norm.var * norm.count + batch_var * n + jnp.square(delta) * norm.count * frac) / jnp.maximum(total, 1.0)
    keep = n <= 0
    return ObsNorm(jnp.where(keep, norm.mean, mean), jnp.where(keep, norm.var, var), total)


def normalize_obs(policy: dict, obs: jax.Array) -> jax.Array:
    """``obs`` standardised by the policy's running statistics (``policy['obs_norm']``), clipped to ±OBS_CLIP.

    The statistics are data, not parameters: no gradient flows into them, so optimisers (PPO's, the meta step's
    outer and inner updates) leave them unchanged.
    """
    norm = jax.lax.stop_gradient(policy["obs_norm"])
    std = jnp.maximum(jnp.sqrt(norm.var), OBS_STD_MIN)
    return jnp.clip((obs - norm.mean) / std, -OBS_CLIP, OBS_CLIP)


class ActorCriticParams(NamedTuple):
    """policy: {'mean': MLP layers, 'log_std': f32[action_size], 'obs_norm': ObsNorm}; value: MLP layers with
    one output, fed the observations normalised by the policy's statistics (``value_of``)."""

    policy: dict
    value: list


def init_actor_critic(rng: jax.Array, obs_size: int, action_size: int, hidden_sizes: Sequence[int],
                      init_std: float) -> ActorCriticParams:
    """Fresh policy (mean MLP with small last layer, log-std = log ``init_std``, identity normaliser) and value
    MLP. ``init_std`` may be a traced scalar (a hyperparameter-grid axis)."""
    k_pi, k_v = jax.random.split(rng)
    sizes = (obs_size, *hidden_sizes)
    policy = {
        "mean": mlp_init(k_pi, (*sizes, action_size), final_scale=0.01),
        "log_std": jnp.full((action_size,), jnp.log(jnp.asarray(init_std, jnp.float32)), dtype=jnp.float32),
        "obs_norm": obs_norm_init(obs_size),
    }
    return ActorCriticParams(policy=policy, value=mlp_init(k_v, (*sizes, 1), final_scale=1.0))


def policy_dist(policy: dict, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Mean f32[..., A] and log-std f32[A] of the Gaussian policy at (raw) ``obs`` f32[..., obs_size].

    A policy with a ``kb`` entry is an *active column* (Progress & Compress, ``column_mean``)."""
    if "kb" in policy:
        return column_mean(policy, obs), policy["log_std"]
    return mlp_apply(policy["mean"], normalize_obs(policy, obs)), policy["log_std"]


def adaptors_init(rng: jax.Array, sizes: Sequence[int]) -> list[dict]:
    """Layer-wise adaptors of an active column whose layers are ``sizes[0] -> ... -> sizes[-1]``: one for every
    layer i >= 2 (its input from the knowledge base is the KB's hidden layer i − 1, of width ``sizes[i - 1]``).

    Adaptor i (Schwarz et al. 2018, eq. 1, after Rusu et al. 2016): ``α_i ⊙ U_i tanh(V_i h^KB_{i−1} + c_i)``, an MLP
    with one hidden layer as wide as its input, and a trainable scale vector α_i ~ U(0, 0.1) of layer i's width.
    """
    out = []
    for i in range(1, len(sizes) - 1):
        n_in, n_out = sizes[i], sizes[i + 1]
        kv, ku, ka = jax.random.split(jax.random.fold_in(rng, i), 3)
        out.append({
            "v": jax.nn.initializers.orthogonal(math.sqrt(2.0))(kv, (n_in, n_in), jnp.float32),
            "c": jnp.zeros((n_in,), jnp.float32),
            "u": jax.nn.initializers.orthogonal(1.0)(ku, (n_in, n_out), jnp.float32),
            "alpha": jax.random.uniform(ka, (n_out,), jnp.float32, 0.0, 0.1),
        })
    return out


def kb_features(kb: dict, obs: jax.Array) -> list[jax.Array]:
    """The hidden activations h^KB_1 … h^KB_{L−1} of the knowledge base's mean MLP at raw ``obs`` (its own
    observation statistics), with no gradient into the knowledge base."""
    kb = jax.lax.stop_gradient(kb)
    h = normalize_obs(kb, obs)
    feats = []
    for layer in kb["mean"][:-1]:
        h = jnp.tanh(h @ layer["w"] + layer["b"])
        feats.append(h)
    return feats


def column_mean(policy: dict, obs: jax.Array) -> jax.Array:
    """Action mean f32[..., A] of an active column: ``policy['mean']`` layers, with adaptor i adding
    ``α_i ⊙ U_i tanh(V_i h^KB_{i−1} + c_i)`` to layer i's pre-activation (i >= 2; the last layer is linear).

    ``policy['kb']`` (the frozen knowledge base, a plain policy) gets no gradient: the lateral connections carry
    gradient into the active column and its adaptors only.
    """
    lead = obs.shape[:-1]
    obs = obs.reshape((-1, obs.shape[-1]))
    feats = kb_features(policy["kb"], obs)
    h = normalize_obs(policy, obs)
    layers = policy["mean"]
    for i, layer in enumerate(layers):
        pre = h @ layer["w"] + layer["b"]
        if i >= 1:
            a = policy["adaptors"][i - 1]
            pre = pre + a["alpha"] * (jnp.tanh(feats[i - 1] @ a["v"] + a["c"]) @ a["u"])
        h = pre if i == len(layers) - 1 else jnp.tanh(pre)
    return h.reshape(lead + h.shape[-1:])


def gaussian_log_prob(mean: jax.Array, log_std: jax.Array, action: jax.Array) -> jax.Array:
    """log N(action; mean, exp(log_std)²), summed over the last (action) axis."""
    z = (action - mean) * jnp.exp(-log_std)
    return jnp.sum(-0.5 * jnp.square(z) - log_std - 0.5 * LOG_2PI, axis=-1)


def gaussian_entropy(log_std: jax.Array) -> jax.Array:
    """Entropy of the diagonal Gaussian with ``log_std`` f32[A]."""
    return jnp.sum(log_std + 0.5 * (LOG_2PI + 1.0))


def policy_log_prob(policy: dict, obs: jax.Array, action: jax.Array) -> jax.Array:
    """log π(action | obs) f32[...] for batched ``obs`` f32[..., obs_size] and ``action`` f32[..., A]."""
    mean, log_std = policy_dist(policy, obs)
    return gaussian_log_prob(mean, log_std, action)


def sample_action(policy: dict, obs: jax.Array, rng: jax.Array) -> tuple[jax.Array, jax.Array]:
    """An action f32[..., A] drawn from π(· | obs) and its log-probability f32[...]."""
    mean, _ = policy_dist(policy, obs)
    return action_from_noise(policy, obs, jax.random.normal(rng, mean.shape, mean.dtype))


def action_from_noise(policy: dict, obs: jax.Array, noise: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The action mean + std·noise for standard-normal ``noise`` f32[..., A], and its log-probability f32[...].

    Rollouts draw all their noise in one call before the time loop, which keeps random-number generation out of
    the per-step work; the log-probability comes from the noise directly.
    """
    mean, log_std = policy_dist(policy, obs)
    action = mean + jnp.exp(log_std) * noise
    log_prob = jnp.sum(-0.5 * jnp.square(noise) - log_std - 0.5 * LOG_2PI, axis=-1)
    return action, log_prob


action_from_noise.host_kind = "gaussian"  # its NumPy twin, for host-simulated families (jcomps.host_acting)


def value_apply(value: list, obs: jax.Array) -> jax.Array:
    """V(obs) f32[...] for ``obs`` f32[..., obs_size] as the network sees it (already normalised)."""
    return mlp_apply(value, obs)[..., 0]


def value_of(params: ActorCriticParams, obs: jax.Array) -> jax.Array:
    """V(obs) f32[...] for raw ``obs``, normalised by the policy's running statistics."""
    return value_apply(params.value, normalize_obs(params.policy, obs))
