"""NumPy twins of the policies' ``act`` functions, for families that simulate on the host (MetaWorld).

A host-simulated family runs whole rollouts where its simulator lives (``Family.host_rollout``): each worker
process steps its share of the episodes for all T_max steps and evaluates the policy itself, so a rollout costs
one round trip instead of one ``pure_callback`` and one worker round trip per step (measured in
docs/design.md, "MetaWorld on the host"). The worker has no JAX, so the policy is evaluated here, in NumPy, by
the twin of the ``act`` function the method uses. An ``acting.Actor`` names its twin (``host_kind``:
``"gaussian"`` for ``networks.GAUSSIAN``, ``"pnc_column"`` for Progress & Compress's active column, ``"tanh_gaussian"``
for PEARL's); an actor without one (a user's own) makes ``acting.rollout`` fall back to stepping through the
family's per-step ``step``.

Policies arrive as plain containers (``plain``: dicts, lists and NumPy arrays, so they pickle without jcomps
classes) of one policy, no leading axes. Every product is computed row by row (``_dense``), so an episode's
actions do not depend on which other episodes share its batch: a rollout is the same whatever the number of
workers it is split over. The twins compute in float32, as the JAX policies do; they agree with them to float32
rounding (tests/test_metaworld.py checks each), not bit for bit, which is all a behaviour policy needs: the
trajectory records the actions taken and their log-probabilities.

This module imports NumPy only.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

LOG_2PI = np.float32(math.log(2.0 * math.pi))
OBS_CLIP = np.float32(10.0)  # networks.OBS_CLIP
OBS_STD_MIN = np.float32(1e-3)  # networks.OBS_STD_MIN


def plain(tree: Any) -> Any:
    """``tree`` with NamedTuples turned into dicts, tuples into lists and leaves into NumPy arrays."""
    if hasattr(tree, "_asdict"):
        return {k: plain(v) for k, v in tree._asdict().items()}
    if isinstance(tree, dict):
        return {k: plain(v) for k, v in tree.items()}
    if isinstance(tree, (list, tuple)):
        return [plain(v) for v in tree]
    return np.asarray(tree)


def _dense(x: np.ndarray, w: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``x @ w + b`` for rows ``x`` f32[n, k], one row at a time (a batch-size-independent product)."""
    return np.matmul(x[:, None, :], w)[:, 0] + b


def _normalize(policy: dict, obs: np.ndarray) -> np.ndarray:
    norm = policy["obs_norm"]
    std = np.maximum(np.sqrt(norm["var"]), OBS_STD_MIN)
    return np.clip((obs - norm["mean"]) / std, -OBS_CLIP, OBS_CLIP)


def _mlp_mean(policy: dict, obs: np.ndarray) -> np.ndarray:
    h = _normalize(policy, obs)
    layers = policy["mean"]
    for layer in layers[:-1]:
        h = np.tanh(_dense(h, layer["w"], layer["b"]))
    return _dense(h, layers[-1]["w"], layers[-1]["b"])


def _column_mean(policy: dict, obs: np.ndarray) -> np.ndarray:
    """``pnc.column_mean``: an active column with lateral adaptors from its knowledge base."""
    kb = policy["kb"]
    feats, h = [], _normalize(kb, obs)
    for layer in kb["mean"][:-1]:
        h = np.tanh(_dense(h, layer["w"], layer["b"]))
        feats.append(h)
    h = _normalize(policy, obs)
    layers = policy["mean"]
    for i, layer in enumerate(layers):
        pre = _dense(h, layer["w"], layer["b"])
        if i >= 1:
            a = policy["adaptors"][i - 1]
            lateral = _dense(np.tanh(_dense(feats[i - 1], a["v"], a["c"])), a["u"], np.float32(0.0))
            pre = pre + a["alpha"] * lateral
        h = pre if i == len(layers) - 1 else np.tanh(pre)
    return h


def _from_noise(mean: np.ndarray, log_std: np.ndarray, noise: np.ndarray):
    """``networks.PolicyFns.act``: mean + exp(log_std)·noise, with the noise's Gaussian log-probability."""
    action = mean + np.exp(log_std) * noise
    log_prob = np.sum(np.float32(-0.5) * np.square(noise) - log_std - np.float32(0.5) * LOG_2PI, axis=-1)
    return action, log_prob


def gaussian(policy: dict, obs: np.ndarray, noise: np.ndarray, episode: np.ndarray):
    """``networks.GAUSSIAN.act``: the Gaussian MLP policy."""
    del episode
    return _from_noise(_mlp_mean(policy, obs), policy["log_std"], noise)


def pnc_column(policy: dict, obs: np.ndarray, noise: np.ndarray, episode: np.ndarray):
    """``pnc.COLUMN.act``: Progress & Compress's active column (its ``kb`` entry the knowledge base)."""
    del episode
    return _from_noise(_column_mean(policy, obs), policy["log_std"], noise)


def _softplus(x: np.ndarray) -> np.ndarray:
    return np.logaddexp(x, np.float32(0.0))


def tanh_gaussian(policy: dict, obs: np.ndarray, noise: np.ndarray, episode: np.ndarray):
    """PEARL's ``act`` (``pearl.make_act``): brax's ReLU MLP on [obs, z] gives (loc, scale); the action is
    tanh(loc + (softplus(scale) + 0.001)·noise) and its log-probability has the tanh correction."""
    z = policy["z"]
    z = z[episode] if z.ndim == 2 else np.broadcast_to(z, (len(obs), z.shape[-1]))
    h = np.concatenate([obs, z.astype(np.float32)], axis=-1)
    net = policy["net"]["params"]
    names = sorted(net, key=lambda k: int(k.split("_")[-1]))
    for i, name in enumerate(names):
        h = _dense(h, net[name]["kernel"], net[name]["bias"])
        if i < len(names) - 1:
            h = np.maximum(h, np.float32(0.0))
    loc, raw_scale = np.split(h, 2, axis=-1)
    scale = _softplus(raw_scale) + np.float32(0.001)
    pre = loc + scale * noise
    log_prob = (-0.5 * np.square(pre / scale - loc / scale) - (np.float32(0.5) * LOG_2PI + np.log(scale))
                - 2.0 * (np.float32(math.log(2.0)) - pre - _softplus(np.float32(-2.0) * pre)))
    return np.tanh(pre), np.sum(log_prob, axis=-1, dtype=np.float32)


TWINS: dict[str, Callable] = {"gaussian": gaussian, "pnc_column": pnc_column, "tanh_gaussian": tanh_gaussian}
"""``host_kind`` -> twin ``(policy, obs f32[n, O], noise f32[n, A], episode i32[n]) -> (action f32[n, A],
log_prob f32[n])``; ``episode`` is each row's episode within its rollout (for per-episode policy entries such
as PEARL's z)."""


def act(kind: str, policy: dict, obs: np.ndarray, noise: np.ndarray, episode: np.ndarray):
    """The twin ``kind`` on rows ``obs``; float32 in, float32 out."""
    if kind not in TWINS:
        raise ValueError(f"no host twin of kind {kind!r}; known: {sorted(TWINS)}")
    action, log_prob = TWINS[kind](policy, np.asarray(obs, np.float32), np.asarray(noise, np.float32), episode)
    return action.astype(np.float32, copy=False), log_prob.astype(np.float32, copy=False)
