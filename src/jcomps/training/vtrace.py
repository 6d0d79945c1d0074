"""V-trace off-policy value targets and policy-gradient advantages (Espeholt et al., 2018; CoMPS Eq. 3).

    v_s = V(x_s) + Σ_{t≥s} (Π_{i=s}^{t-1} γ_i c_i) ρ_t δ_t,    δ_t = r_t + γ_t V(x_{t+1}) − V(x_t),
    ρ_t = min(ρ̄, π(a_t|x_t)/μ(a_t|x_t)),    c_i = λ · min(c̄, π(a_i|x_i)/μ(a_i|x_i)).

ρ̄ and c̄ are separate hyperparameters (rlax fixes c̄ = 1; CoMPS does not). Discounts γ_t are per step, 0 at an
episode end, which cuts the traces there.
"""

from __future__ import annotations

from typing import NamedTuple

import chex
import jax
import jax.numpy as jnp


class VTraceOutput(NamedTuple):
    """Outputs of ``vtrace``, all f32[T, B] and free of gradients.

    Attributes:
      vs: V-trace value targets v_s.
      pg_advantages: clipped-ρ policy-gradient advantages min(ρ̄_pg, r_t)·(r_t + γ_t·v_{t+1} − V(x_t)), with
        v_T = bootstrap_value.
      clipped_rhos: ρ_t = min(ρ̄, importance weight).
      clipped_pg_rhos: min(ρ̄_pg, importance weight), the factor in ``pg_advantages``.
    """

    vs: jax.Array
    pg_advantages: jax.Array
    clipped_rhos: jax.Array
    clipped_pg_rhos: jax.Array


def vtrace(values, bootstrap_value, rewards, discounts, log_rhos, *, rho_bar: float = 1.0, c_bar: float = 1.0,
           pg_rho_bar: float = 1.0, lambda_: float = 1.0) -> VTraceOutput:
    """V-trace targets and advantages for time-major trajectories.

    Args:
      values: f32[T, B], V(x_t) under the current value function.
      bootstrap_value: f32[B], V(x_T), the value of the state after the last step.
      rewards: f32[T, B], r_t.
      discounts: f32[T, B], γ_t: the discount times 0 where step t ended an episode (termination).
      log_rhos: f32[T, B], log π(a_t|x_t) − log μ(a_t|x_t) (target minus behaviour log-probability).
      rho_bar: ρ̄, clip of the importance weight in the value targets' TD errors.
      c_bar: c̄, clip of the trace-cutting coefficients.
      pg_rho_bar: clip of the importance weight in the policy-gradient advantages.
      lambda_: λ, scales the traces (λ = 1 is V-trace as published).

    Returns:
      ``VTraceOutput``; gradients are stopped through every output (they are targets and weights).
    """
    chex.assert_rank([values, bootstrap_value, rewards, discounts, log_rhos], [2, 1, 2, 2, 2])
    chex.assert_equal_shape([values, rewards, discounts, log_rhos])
    chex.assert_type([values, bootstrap_value, rewards, discounts, log_rhos], float)
    values, bootstrap_value, rewards, discounts, log_rhos = jax.lax.stop_gradient(
        (values, bootstrap_value, rewards, discounts, log_rhos))
    rhos = jnp.exp(log_rhos)
    clipped_rhos = jnp.minimum(rho_bar, rhos)
    cs = lambda_ * jnp.minimum(c_bar, rhos)
    next_values = jnp.concatenate([values[1:], bootstrap_value[None]], axis=0)
    deltas = clipped_rhos * (rewards + discounts * next_values - values)

    def body(acc, xs):
        delta, discount, c = xs
        acc = delta + discount * c * acc
        return acc, acc

    _, vs_minus_v = jax.lax.scan(body, jnp.zeros_like(bootstrap_value), (deltas, discounts, cs), reverse=True)
    vs = vs_minus_v + values
    next_vs = jnp.concatenate([vs[1:], bootstrap_value[None]], axis=0)
    clipped_pg_rhos = jnp.minimum(pg_rho_bar, rhos)
    pg_advantages = clipped_pg_rhos * (rewards + discounts * next_vs - values)
    return VTraceOutput(vs, pg_advantages, clipped_rhos, clipped_pg_rhos)


def discounted_returns(rewards, discounts, bootstrap_value):
    """Bootstrapped discounted returns G_t = r_t + γ_t G_{t+1}, G_T = ``bootstrap_value`` (f32[T, B] from
    time-major ``rewards`` and per-step ``discounts`` f32[T, B], 0 at a termination). On-policy V-trace with λ = 1
    gives the same targets whatever the values (``vtrace(...).vs``; tested); GAE (``jcomps.training.ppo.gae``) is
    on-policy V-trace with traces c = λ."""
    chex.assert_rank([rewards, discounts, bootstrap_value], [2, 2, 1])

    def body(acc, xs):
        reward, discount = xs
        acc = reward + discount * acc
        return acc, acc

    _, returns = jax.lax.scan(body, bootstrap_value, (rewards, discounts), reverse=True)
    return returns
