"""Small numerics shared by every part of jcomps (as ``optax._src.numerics`` is for optax): masked means, variances
and standardisation, finiteness checks, the one optimiser step every method makes (``guarded_update``: skipped,
never applied, when it is not finite), and the config-field check behind every config error."""

from __future__ import annotations

import math
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np
import optax


def check_field(ok: bool, field: str, value, allowed: str):
    """Raises ValueError naming ``field``, its ``value`` and what is ``allowed`` unless ``ok`` (NaN is never ok)."""
    if not ok or isinstance(value, float) and math.isnan(value):
        raise ValueError(f"invalid config value {field}={value!r}; allowed: {allowed}")


def holds_tracers(config) -> bool:
    """Whether a field of the config dataclass ``config`` holds a traced value: a hyperparameter-grid axis's
    member value inside a compiled program (``jcomps.runner.grid.with_traced``). Its ``__post_init__`` then skips
    its checks, which cannot compare tracers; every value of the axis was checked concretely beforehand
    (``jcomps.runner.grid.points``)."""
    import dataclasses

    return any(isinstance(getattr(config, f.name), jax.core.Tracer) for f in dataclasses.fields(config))


def check_finite_fields(config) -> None:
    """Raises ValueError naming the first field of the config dataclass ``config`` (nested configs are checked by
    their own ``__post_init__``) that holds a NaN or an infinity, alone or inside a tuple: no config field takes
    one (an infinite learning rate would make every update non-finite, and every update would then be skipped)."""
    import dataclasses

    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        values = value if isinstance(value, tuple) else (value,)
        for v in values:
            if isinstance(v, (float, np.floating)) and not math.isfinite(v):
                raise ValueError(f"invalid config value {f.name}={value!r}; allowed: a finite number")


def masked_mean(x, mask):
    """Mean of ``x`` over entries where ``mask`` is 1 (0 when the mask is empty)."""
    return jnp.sum(x * mask) / jnp.maximum(jnp.sum(mask), 1.0)


def masked_weights(mask):
    """``mask`` divided by its count (at least 1): the weights whose dot product with ``x`` is ``x``'s masked mean,
    for losses that weigh rows before summing them."""
    return mask / jnp.maximum(jnp.sum(mask), 1.0)


def masked_var(x, mask, mean=None):
    """Variance of ``x`` over entries where ``mask`` is 1, about ``mean`` (default: the masked mean)."""
    mean = masked_mean(x, mask) if mean is None else mean
    return masked_mean(jnp.square(x - mean), mask)


def masked_standardize(x, mask, eps: float = 1e-8):
    """``x`` minus its masked mean, divided by its masked standard deviation + ``eps`` (advantage normalisation)."""
    mean = masked_mean(x, mask)
    return (x - mean) / (jnp.sqrt(masked_var(x, mask, mean)) + eps)


def masked_explained_variance(target, prediction, mask):
    """1 − Var(target − prediction) / Var(target) over the valid samples (the critic diagnostic Stable-Baselines and
    CleanRL log for PPO): 1 for a perfect fit, 0 for a constant at the targets' mean, negative for worse than that.
    Var(target) is floored at 1e-8, so constant targets give a large negative value unless the fit is exact."""
    return 1.0 - masked_var(target - prediction, mask) / jnp.maximum(masked_var(target, mask), 1e-8)


def all_finite(tree) -> jax.Array:
    """bool[]: whether every leaf of ``tree`` is free of NaN and infinity."""
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(tree)]))


def concrete_max(x) -> Optional[int]:
    """The largest value of the integer array ``x`` when it is concrete; None while it is being traced (a check
    on it cannot run then)."""
    if isinstance(x, jax.core.Tracer):
        return None
    return int(np.max(np.asarray(x)))


def keep_if_finite(finite: jax.Array, new, old):
    """``new`` where the bool[] ``finite`` holds, else ``old`` (same pytree structure): an update computed from a
    NaN or infinite loss or gradient is skipped, never applied (as optax's ``apply_if_finite``)."""
    return jax.tree.map(lambda a, b: jnp.where(finite, a, b), new, old)


def optimizer_step(optimizer: optax.GradientTransformation, grads, opt_state, params):
    """One step of ``optimizer``: (new params, new optimiser state). Unguarded: for steps that are guarded together
    (``keep_if_finite`` over all of them), as PEARL's three and the meta step's two."""
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state


def guarded_update(optimizer: optax.GradientTransformation, grads, opt_state, params, loss=()):
    """One step of ``optimizer``, applied only if ``grads`` and ``loss`` (any pytree) are finite, as optax's
    ``apply_if_finite`` (whose ``total_notfinite`` is our per-iteration ``nonfinite``). Returns (params, opt_state,
    finite bool[]): the old ones where not finite."""
    finite = all_finite((loss, grads))
    new = optimizer_step(optimizer, grads, opt_state, params)
    params, opt_state = keep_if_finite(finite, new, (params, opt_state))
    return params, opt_state, finite
