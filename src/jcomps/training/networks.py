"""Networks: a Gaussian MLP policy with a state-independent log-std, and an MLP value function.

Parameters are plain pytrees (nested dicts of arrays) so they can be differentiated through, stacked over
seeds and tasks, and checkpointed without any object state. How a policy is applied is data too (``PolicyFns``,
as brax's ``make_inference_fn``): ``GAUSSIAN`` for the MLP policy here; a method with its own network brings its
own (Progress & Compress's active column, ``jcomps.methods.pnc.COLUMN``).
"""

from __future__ import annotations

import math
from typing import Any, Callable, NamedTuple, Optional, Sequence

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
    """Mean f32[..., A] and log-std f32[A] of the Gaussian MLP policy at (raw) ``obs`` f32[..., obs_size]."""
    return mlp_apply(policy["mean"], normalize_obs(policy, obs)), policy["log_std"]


def policy_hidden(policy: dict, obs: jax.Array) -> list[jax.Array]:
    """The tanh hidden activations f32[..., width] of the Gaussian MLP policy's mean network at (raw) ``obs``, one
    array per hidden layer (what the plasticity measures read, ``jcomps.training.plasticity``)."""
    h, out = normalize_obs(policy, obs), []
    for layer in policy["mean"][:-1]:
        h = mlp_features([layer], h)
        out.append(h)
    return out


STD_MODES = ("learnt", "fixed", "reset")
"""How a policy's state-independent exploration std is treated (``jcomps.training.ppo.PPOConfig.std_mode``)."""


def held_std(policy: dict) -> dict:
    """``policy`` with its log-std a constant of any gradient taken through the result: no update (an optimiser's, an
    inner step's, a distillation's) can move it, and Adam, whose moments then stay zero, leaves it bit for bit."""
    return {**policy, "log_std": jax.lax.stop_gradient(policy["log_std"])}


def with_std(policy: dict, std) -> dict:
    """``policy`` with its std set to ``std`` (a scalar, may be traced) in every action dimension."""
    log_std = jnp.log(jnp.asarray(std, jnp.float32))
    return {**policy, "log_std": jnp.full(policy["log_std"].shape, log_std, dtype=jnp.float32)}


def gaussian_log_prob(mean: jax.Array, log_std: jax.Array, action: jax.Array) -> jax.Array:
    """log N(action; mean, exp(log_std)²), summed over the last (action) axis."""
    z = (action - mean) * jnp.exp(-log_std)
    return jnp.sum(-0.5 * jnp.square(z) - log_std - 0.5 * LOG_2PI, axis=-1)


def gaussian_entropy(log_std: jax.Array) -> jax.Array:
    """Entropy of the diagonal Gaussian with ``log_std`` f32[..., A], summed over the last (action) axis."""
    return jnp.sum(log_std + 0.5 * (LOG_2PI + 1.0), axis=-1)


class PolicyFns(NamedTuple):
    """How a diagonal-Gaussian policy is applied (as brax's ``make_inference_fn``): the method that owns the policy's
    network brings its ``dist``; log-probabilities and actions derive from it.

    Attributes:
      dist: ``(policy, obs f32[..., obs_size]) -> (mean f32[..., A], log_std f32[A])`` at raw observations.
      host_kind: the name of ``act``'s NumPy twin (``jcomps.envs.host_acting.TWINS``), with which a family simulated on
        the host runs whole rollouts there; None: no twin (such a family is stepped through its ``step``).
      hidden: ``(policy, obs f32[..., obs_size]) -> [f32[..., width] per hidden layer]``, the mean network's tanh
        activations (the plasticity measures' input); None: not measured.
    """

    dist: Callable[[Any, jax.Array], tuple[jax.Array, jax.Array]]
    host_kind: Optional[str] = None
    hidden: Optional[Callable[[Any, jax.Array], list]] = None

    def log_prob(self, policy, obs: jax.Array, action: jax.Array) -> jax.Array:
        """log π(action | obs) f32[...] for ``obs`` f32[..., obs_size] and ``action`` f32[..., A]."""
        mean, log_std = self.dist(policy, obs)
        return gaussian_log_prob(mean, log_std, action)

    def act(self, policy, obs: jax.Array, noise: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The action mean + std·noise f32[..., A] for standard-normal ``noise`` f32[..., A], and its
        log-probability f32[...] (an ``acting.ActFn``).

        Rollouts draw all their noise in one call before the time loop, which keeps random-number generation out of
        the per-step work; the log-probability comes from the noise directly.
        """
        mean, log_std = self.dist(policy, obs)
        action = mean + jnp.exp(log_std) * noise
        log_prob = jnp.sum(-0.5 * jnp.square(noise) - log_std - 0.5 * LOG_2PI, axis=-1)
        return action, log_prob


GAUSSIAN = PolicyFns(policy_dist, host_kind="gaussian", hidden=policy_hidden)
"""The Gaussian MLP policy of ``init_actor_critic`` (``policy_dist``); its twin is
``jcomps.envs.host_acting.gaussian``."""


def value_apply(value: list, obs: jax.Array) -> jax.Array:
    """V(obs) f32[...] for ``obs`` f32[..., obs_size] as the network sees it (already normalised)."""
    return mlp_apply(value, obs)[..., 0]


def value_of(params: ActorCriticParams, obs: jax.Array) -> jax.Array:
    """V(obs) f32[...] for raw ``obs``, normalised by the policy's running statistics."""
    return value_apply(params.value, normalize_obs(params.policy, obs))
