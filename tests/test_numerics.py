"""Laws of the shared numerics: masked statistics equal numpy's on the masked entries, the guarded update is one
plain optimiser step when finite and no step at all otherwise, and config errors name their field."""

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from jcomps import numerics

_values = hnp.arrays(np.float32, st.integers(1, 12), elements=st.floats(-100, 100, width=32))


def _mask_for(x, bits):
    """f32 mask of ``x``'s length from the hypothesis draw ``bits`` (cycled)."""
    return np.resize(np.asarray(bits, np.float32), x.shape)


@given(_values, st.lists(st.booleans(), min_size=1, max_size=12))
def test_masked_statistics_are_numpys_on_the_masked_entries(x, bits):
    mask = _mask_for(x, bits)
    kept = x[mask > 0].astype(np.float64)
    if kept.size == 0:
        expected_mean = expected_var = 0.0
    else:
        expected_mean, expected_var = kept.mean(), kept.var()
    np.testing.assert_allclose(numerics.masked_mean(x, mask), expected_mean, rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(numerics.masked_var(x, mask), expected_var, rtol=1e-4, atol=1e-2)
    standardized = np.asarray(numerics.masked_standardize(x, mask))
    assert np.all(np.isfinite(standardized))
    if kept.size > 0 and np.sqrt(expected_var) > 0.1:  # a spread well above float32 rounding
        expected = (x.astype(np.float64) - expected_mean) / (np.sqrt(expected_var) + 1e-8)
        np.testing.assert_allclose(standardized[mask > 0], expected[mask > 0], rtol=1e-3, atol=1e-3)


def test_masked_standardize_gives_zero_mean_unit_variance_on_the_masked_entries():
    x = jnp.array([3.0, -1.0, 100.0, 2.0, 7.0, -50.0])
    mask = jnp.array([1.0, 1.0, 0.0, 1.0, 1.0, 0.0])
    z = numerics.masked_standardize(x, mask)
    np.testing.assert_allclose(numerics.masked_mean(z, mask), 0.0, atol=1e-6)
    np.testing.assert_allclose(numerics.masked_var(z, mask), 1.0, rtol=1e-5)


def test_masked_var_about_a_given_mean():
    x, mask = jnp.array([1.0, 2.0, 3.0, 40.0]), jnp.array([1.0, 1.0, 1.0, 0.0])
    np.testing.assert_allclose(numerics.masked_var(x, mask, mean=0.0), (1 + 4 + 9) / 3, rtol=1e-6)


def test_an_empty_mask_gives_zeros():
    x, empty = jnp.array([1.0, -2.0, 5.0]), jnp.zeros(3)
    assert float(numerics.masked_mean(x, empty)) == 0.0
    assert float(numerics.masked_var(x, empty)) == 0.0
    assert np.all(np.isfinite(numerics.masked_standardize(x, empty)))
    np.testing.assert_array_equal(numerics.masked_weights(empty), np.zeros(3))


@given(_values, st.lists(st.booleans(), min_size=1, max_size=12))
def test_masked_weights_sum_to_one_and_weigh_into_the_masked_mean(x, bits):
    mask = _mask_for(x, bits)
    weights = np.asarray(numerics.masked_weights(mask))
    np.testing.assert_allclose(weights.sum(), 1.0 if mask.any() else 0.0, rtol=1e-6)
    np.testing.assert_array_equal(weights[mask == 0], 0.0)
    np.testing.assert_allclose(jnp.dot(weights, x), numerics.masked_mean(x, mask), rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("bad", [jnp.nan, jnp.inf, -jnp.inf])
def test_all_finite_finds_a_non_finite_value_in_any_leaf(bad):
    tree = {"a": jnp.ones((2, 3)), "b": (jnp.zeros(4), jnp.float32(1.0))}
    assert bool(numerics.all_finite(tree))
    assert not bool(numerics.all_finite({**tree, "b": (jnp.zeros(4).at[2].set(bad), jnp.float32(1.0))}))
    assert not bool(numerics.all_finite({**tree, "c": jnp.float32(bad)}))
    chex.assert_shape(numerics.all_finite(tree), ())


def test_keep_if_finite_picks_the_whole_new_or_old_tree():
    new, old = {"w": jnp.ones(3), "b": jnp.float32(2.0)}, {"w": jnp.zeros(3), "b": jnp.float32(-1.0)}
    chex.assert_trees_all_equal(numerics.keep_if_finite(jnp.array(True), new, old), new)
    chex.assert_trees_all_equal(numerics.keep_if_finite(jnp.array(False), new, old), old)


def _problem():
    """Parameters, gradients and an Adam optimiser (after one step, so its state is not the initial one)."""
    params = {"w": jnp.array([0.5, -1.0, 2.0]), "b": jnp.float32(0.1)}
    grads = {"w": jnp.array([0.3, -0.2, 1.0]), "b": jnp.float32(-0.4)}
    optimizer = optax.adam(1e-2)
    state = optimizer.update(grads, optimizer.init(params), params)[1]
    return optimizer, grads, state, params


def test_optimizer_step_is_optaxs_update_and_apply():
    optimizer, grads, state, params = _problem()
    updates, expected_state = optimizer.update(grads, state, params)
    new_params, new_state = numerics.optimizer_step(optimizer, grads, state, params)
    chex.assert_trees_all_equal(new_params, optax.apply_updates(params, updates))
    chex.assert_trees_all_equal(new_state, expected_state)


def test_a_finite_guarded_update_is_one_plain_step():
    optimizer, grads, state, params = _problem()
    new_params, new_state, finite = jax.jit(numerics.guarded_update, static_argnums=0)(
        optimizer, grads, state, params, jnp.float32(1.5))
    assert bool(finite)
    expected = numerics.optimizer_step(optimizer, grads, state, params)
    chex.assert_trees_all_close(new_params, expected[0], rtol=1e-6)
    chex.assert_trees_all_close(new_state, expected[1], rtol=1e-6)
    assert not np.allclose(new_params["w"], params["w"])


@pytest.mark.parametrize("where", ["grad", "loss"])
def test_a_non_finite_guarded_update_changes_nothing(where):
    optimizer, grads, state, params = _problem()
    loss = jnp.float32(1.5)
    if where == "grad":
        grads = {**grads, "w": grads["w"].at[1].set(jnp.nan)}
    else:
        loss = jnp.float32(jnp.nan)
    new_params, new_state, finite = numerics.guarded_update(optimizer, grads, state, params, loss)
    assert not bool(finite)
    chex.assert_trees_all_equal(new_params, params)
    chex.assert_trees_all_equal(new_state, state)


@dataclasses.dataclass(frozen=True)
class _Config:
    rate: float = 0.1
    sizes: tuple = (1.0, 2.0)

    def __post_init__(self):
        numerics.check_finite_fields(self)


def test_check_field_names_the_field_and_what_is_allowed():
    numerics.check_field(True, "rate", 0.1, "a number")
    with pytest.raises(ValueError, match=r"rate=-1.*allowed: a positive number"):
        numerics.check_field(False, "rate", -1, "a positive number")
    with pytest.raises(ValueError, match=r"rate=nan"):
        numerics.check_field(True, "rate", float("nan"), "a number")


@pytest.mark.parametrize("field, value", [("rate", float("inf")), ("rate", np.float32("nan")),
                                          ("sizes", (1.0, float("-inf")))])
def test_check_finite_fields_names_the_field(field, value):
    _Config()
    with pytest.raises(ValueError, match=rf"{field}=.*allowed: a finite number"):
        _Config(**{field: value})


def test_concrete_max_is_the_max_or_none_while_traced():
    assert numerics.concrete_max(jnp.array([3, 7, 2])) == 7
    assert numerics.concrete_max(np.int32(4)) == 4
    seen = []
    jax.jit(lambda x: seen.append(numerics.concrete_max(x)) or x)(jnp.array([1, 2]))
    assert seen == [None]


def test_explained_variance_laws():
    rng = np.random.default_rng(0)
    target = rng.normal(size=50).astype(np.float32)
    mask = np.ones(50, np.float32)
    np.testing.assert_allclose(numerics.masked_explained_variance(target, target, mask), 1.0, atol=1e-6)
    np.testing.assert_allclose(numerics.masked_explained_variance(target, np.full(50, target.mean()), mask), 0.0,
                               atol=1e-5)
    # Masked samples count for nothing, however wrong.
    mask[:10] = 0.0
    wrong = target.copy()
    wrong[:10] = 1e3
    np.testing.assert_allclose(numerics.masked_explained_variance(target, wrong, mask), 1.0, atol=1e-6)
