"""Laws of V-trace: on-policy it is the bootstrapped discounted return, episode ends split traces, clipping
bounds hold, it matches the paper's sum formula, and jit and no-jit agree."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from jcomps.training import ppo
from jcomps.training.vtrace import discounted_returns, vtrace


def _inputs(seed, T=6, B=3, scale=1.0):
    rng = np.random.default_rng(seed)
    f = lambda *s: rng.normal(size=s).astype(np.float32)  # noqa: E731
    discounts = (0.9 * (rng.uniform(size=(T, B)) > 0.2)).astype(np.float32)
    return dict(values=f(T, B), bootstrap_value=f(B), rewards=f(T, B), discounts=discounts,
                log_rhos=scale * f(T, B))


def _reference(values, bootstrap_value, rewards, discounts, log_rhos, rho_bar, c_bar, lambda_):
    """The paper's Eq. 3 written as the explicit double sum."""
    T = len(values)
    rhos = np.exp(log_rhos.astype(np.float64))
    next_v = np.concatenate([values[1:], bootstrap_value[None]])
    deltas = np.minimum(rho_bar, rhos) * (rewards + discounts * next_v - values)
    cs = lambda_ * np.minimum(c_bar, rhos)
    vs = np.array(values, np.float64)
    for s in range(T):
        prod = np.ones_like(bootstrap_value, np.float64)
        for t in range(s, T):
            vs[s] += prod * deltas[t]
            prod = prod * discounts[t] * cs[t]
    return vs


class VTraceTest(chex.TestCase):

    @chex.variants(with_jit=True, without_jit=True)
    def test_on_policy_equals_bootstrapped_discounted_return(self):
        x = _inputs(0)
        x["log_rhos"] = np.zeros_like(x["log_rhos"])
        out = self.variant(vtrace)(**x)
        ret = np.zeros_like(x["values"])
        acc = x["bootstrap_value"]
        for t in reversed(range(len(ret))):
            acc = x["rewards"][t] + x["discounts"][t] * acc
            ret[t] = acc
        chex.assert_trees_all_close(out.vs, ret, rtol=1e-5, atol=1e-5)

    @chex.variants(with_jit=True, without_jit=True)
    def test_matches_the_papers_sum_formula(self):
        x = _inputs(1, scale=0.8)
        out = self.variant(lambda **k: vtrace(**k, rho_bar=1.2, c_bar=0.7, pg_rho_bar=0.9, lambda_=0.95))(**x)
        ref = _reference(**x, rho_bar=1.2, c_bar=0.7, lambda_=0.95)
        chex.assert_trees_all_close(out.vs, ref, rtol=1e-4, atol=1e-4)
        next_vs = np.concatenate([np.asarray(out.vs)[1:], x["bootstrap_value"][None]])
        pg = np.minimum(0.9, np.exp(x["log_rhos"])) * (x["rewards"] + x["discounts"] * next_vs - x["values"])
        chex.assert_trees_all_close(out.pg_advantages, pg, rtol=1e-4, atol=1e-4)

    def test_trace_split_at_episode_end_equals_two_traces(self):
        x = _inputs(2, T=8, scale=0.5)
        x["discounts"] = np.full_like(x["discounts"], 0.9)
        x["discounts"][3] = 0.0  # the episode ends at step 3
        whole = vtrace(**x, rho_bar=1.5, c_bar=0.8)
        first = vtrace(**{k: v[:4] for k, v in x.items() if k != "bootstrap_value"},
                       bootstrap_value=x["values"][4], rho_bar=1.5, c_bar=0.8)
        second = vtrace(**{k: v[4:] for k, v in x.items() if k != "bootstrap_value"},
                        bootstrap_value=x["bootstrap_value"], rho_bar=1.5, c_bar=0.8)
        chex.assert_trees_all_close(whole.vs, jnp.concatenate([first.vs, second.vs]), rtol=1e-5, atol=1e-5)
        chex.assert_trees_all_close(whole.pg_advantages,
                                    jnp.concatenate([first.pg_advantages, second.pg_advantages]), rtol=1e-5,
                                    atol=1e-5)

    def test_rho_bar_and_c_bar_are_separate(self):
        x = _inputs(3, scale=2.0)
        a = vtrace(**x, rho_bar=1.0, c_bar=1.0)
        b = vtrace(**x, rho_bar=1.0, c_bar=0.3)
        chex.assert_trees_all_equal(a.clipped_rhos, b.clipped_rhos)
        assert not np.allclose(a.vs, b.vs)

    def test_vmap_over_an_extra_axis(self):
        xs = [_inputs(s) for s in range(3)]
        stacked = jax.tree.map(lambda *a: np.stack(a), *xs)
        batched = jax.vmap(lambda **k: vtrace(**k))(**stacked)
        for i, x in enumerate(xs):
            chex.assert_trees_all_close(jax.tree.map(lambda a: a[i], batched), vtrace(**x), rtol=1e-6)

    def test_no_gradient_flows_through_outputs(self):
        x = _inputs(4)
        g = jax.grad(lambda lr: jnp.sum(vtrace(**{**x, "log_rhos": lr}).pg_advantages))(x["log_rhos"])
        chex.assert_trees_all_equal(g, jnp.zeros_like(g))


_floats = st.floats(-5.0, 5.0, width=32)


@given(log_rhos=hnp.arrays(np.float32, (5, 2), elements=_floats),
       rho_bar=st.floats(0.1, 3.0), c_bar=st.floats(0.1, 3.0), pg_rho_bar=st.floats(0.1, 3.0))
def test_clipped_weights_never_exceed_their_bounds(log_rhos, rho_bar, c_bar, pg_rho_bar):
    x = _inputs(5, T=5, B=2)
    x["log_rhos"] = log_rhos
    out = vtrace(**x, rho_bar=rho_bar, c_bar=c_bar, pg_rho_bar=pg_rho_bar)
    assert np.all(np.asarray(out.clipped_rhos) <= np.float32(rho_bar) + 1e-6)
    assert np.all(np.asarray(out.clipped_pg_rhos) <= np.float32(pg_rho_bar) + 1e-6)
    assert np.all(np.asarray(out.clipped_rhos) >= 0)
    ref = _reference(**x, rho_bar=rho_bar, c_bar=c_bar, lambda_=1.0)
    np.testing.assert_allclose(np.asarray(out.vs), ref, rtol=1e-3, atol=1e-3)


def test_gae_is_on_policy_vtrace_with_traces_lambda():
    # GAE(λ) advantages are V-trace's v_s − V(x_s) with every importance weight 1 and traces c = λ; the targets are
    # v_s. Terminations (dones) are the zero discounts.
    x = _inputs(11)
    dones = (x["discounts"] == 0).astype(np.float32)
    for lambda_ in (0.0, 0.5, 0.95, 1.0):
        adv, targets = ppo.gae(x["rewards"], x["values"], x["bootstrap_value"], dones, 0.9, lambda_)
        out = vtrace(x["values"], x["bootstrap_value"], x["rewards"], 0.9 * (1 - dones), np.zeros_like(dones),
                     lambda_=lambda_)
        np.testing.assert_allclose(targets, out.vs, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(adv, out.vs - x["values"], rtol=1e-5, atol=1e-5)


def test_discounted_returns_are_on_policy_vtrace_with_lambda_one():
    # With λ = 1 and every weight 1 the values telescope away: v_s is the bootstrapped discounted return.
    x = _inputs(12)
    returns = discounted_returns(x["rewards"], x["discounts"], x["bootstrap_value"])
    for values in (x["values"], np.zeros_like(x["values"]), 10.0 * x["values"]):
        out = vtrace(values, x["bootstrap_value"], x["rewards"], x["discounts"], np.zeros_like(values))
        np.testing.assert_allclose(returns, out.vs, rtol=1e-5, atol=1e-4)
    # And by hand: G_{T-1} = r + γ·bootstrap.
    np.testing.assert_allclose(returns[-1], x["rewards"][-1] + x["discounts"][-1] * x["bootstrap_value"], rtol=1e-6)
