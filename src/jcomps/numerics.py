"""Small numerics shared by every part of jcomps (as ``optax._src.numerics`` is for optax): masked means,
finiteness checks, the skip-if-non-finite update, and the config-field check behind every config error."""

from __future__ import annotations

import math
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np


def check_field(ok: bool, field: str, value, allowed: str):
    """Raises ValueError naming ``field``, its ``value`` and what is ``allowed`` unless ``ok`` (NaN is never ok)."""
    if not ok or isinstance(value, float) and math.isnan(value):
        raise ValueError(f"invalid config value {field}={value!r}; allowed: {allowed}")


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
