"""Laws of the RL loop (``rl_loop.iterate``), driven by fake ``collect``/``update`` functions (no environment): a
counter state and success rates scripted per iteration. It stops at the first iteration at or above the threshold
and makes no update there, never updates on a non-finite batch, fills fixed-size metrics rows, hands out the
documented keys and reports progress with 1-based iterations."""

import functools
from typing import NamedTuple

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from jcomps import progress
from jcomps.training import acting, rl_loop

BUDGET = 6
THRESHOLD = 0.9


class Script(NamedTuple):
    """What each iteration (index 0..BUDGET-1) collects and reports: success f32[BUDGET], finite collection
    bool[BUDGET], update reporting nonfinite bool[BUDGET]."""

    success: jax.Array
    finite: jax.Array
    bad: jax.Array


def script(success, finite=None, bad=None) -> Script:
    """A Script of BUDGET iterations; every collection finite and every update finite unless given."""
    success = jnp.asarray(success, jnp.float32)
    chex.assert_shape(success, (BUDGET,))
    ones = np.ones(BUDGET, bool)
    return Script(success, jnp.asarray(ones if finite is None else finite), jnp.asarray(~ones if bad is None else bad))


class Learner(NamedTuple):
    """The fake learner: collections and updates made, the iterations updated on bool[BUDGET] and the update keys
    u32[BUDGET, 2] (by the iteration whose batch was learnt from)."""

    collected: jax.Array
    updates: jax.Array
    updated_at: jax.Array
    update_keys: jax.Array


class Aux(NamedTuple):
    """The fake accumulator: the collection keys u32[BUDGET, collect_keys, 2] by iteration."""

    collect_keys: jax.Array


def _fakes(s: Script):
    def collect(learner, aux, keys, it):
        aux = Aux(aux.collect_keys.at[it].set(jnp.stack(keys)))
        col = rl_loop.Collected(batch=it, mean_return=-it.astype(jnp.float32), success_rate=s.success[it],
                                finite=s.finite[it])
        return learner._replace(collected=learner.collected + 1), aux, col

    def update(learner, it, key):
        learner = learner._replace(updates=learner.updates + 1, updated_at=learner.updated_at.at[it].set(True),
                                   update_keys=learner.update_keys.at[it].set(key))
        x = (it + 1).astype(jnp.float32)
        return learner, rl_loop.UpdateTerms(x, 2 * x, 3 * x, 4 * x, 5 * x), s.bad[it]

    return collect, update


def _start(collect_keys: int) -> tuple[Learner, Aux]:
    learner = Learner(jnp.int32(0), jnp.int32(0), jnp.zeros(BUDGET, bool), jnp.zeros((BUDGET, 2), jnp.uint32))
    return learner, Aux(jnp.zeros((BUDGET, collect_keys, 2), jnp.uint32))


@functools.cache
def runner(stop_at_threshold: bool = True, run_at_least=None, collect_keys: int = 1):
    """``iterate`` over a Script, jitted once for this configuration (``(script, rng) -> LoopResult``)."""
    def run(s: Script, rng):
        collect, update = _fakes(s)
        learner, aux = _start(collect_keys)
        return rl_loop.iterate(collect, update, learner, rng, threshold=THRESHOLD, budget=BUDGET,
                               collect_keys=collect_keys, aux=aux, stop_at_threshold=stop_at_threshold,
                               run_at_least=run_at_least)

    # chex counts traces by a function's name and source: one name per configuration.
    run.__name__ = f"run_{stop_at_threshold}_{run_at_least}_{collect_keys}"
    return jax.jit(chex.assert_max_traces(run, n=1))


def _run(s: Script, **config) -> rl_loop.LoopResult:
    return runner(**config)(s, jax.random.PRNGKey(0))


def _rows_ran(out: rl_loop.LoopResult) -> int:
    return int(np.sum(out.metrics.valid))


def test_it_stops_at_the_first_success_without_updating_there():
    out = _run(script([0.1, 0.5, 0.95, 0.99, 0.2, 0.3]))
    assert int(out.iterations) == 3 and bool(out.solved)
    np.testing.assert_array_equal(out.state.updated_at, [True, True, False, False, False, False])
    assert int(out.state.updates) == 2 and int(out.state.collected) == 3
    np.testing.assert_array_equal(out.metrics.valid, [True, True, True, False, False, False])
    np.testing.assert_allclose(out.metrics.success_rate, [0.1, 0.5, 0.95, 0, 0, 0])
    np.testing.assert_allclose(out.metrics.mean_return, [0, -1, -2, 0, 0, 0])
    np.testing.assert_allclose(out.metrics.policy_loss, [1, 2, 0, 0, 0, 0])
    np.testing.assert_allclose(out.metrics.approx_kl, [4, 8, 0, 0, 0, 0])
    # The critic's fit is not measured where no update was made (nor in rows that never ran: zeros).
    np.testing.assert_allclose(out.metrics.value_ev, [5, 10, np.nan, 0, 0, 0])
    np.testing.assert_array_equal(out.metrics.nonfinite, np.zeros(BUDGET))


@given(st.lists(st.sampled_from([0.0, 0.3, THRESHOLD, 1.0]), min_size=BUDGET, max_size=BUDGET))
def test_the_stop_is_the_first_success_of_any_curve(curve):
    out = _run(script(curve))
    expected, solved = rl_loop.first_success(jnp.asarray(curve, jnp.float32), THRESHOLD, BUDGET)
    assert int(out.iterations) == int(expected) and bool(out.solved) == bool(solved)
    assert _rows_ran(out) == int(expected)
    assert int(out.state.updates) == int(expected) - int(solved)
    for field in out.metrics:
        np.testing.assert_array_equal(np.asarray(field)[int(expected):], 0)


def test_iterations_is_the_budget_when_never_solved():
    out = _run(script([0.1, 0.2, 0.3, 0.4, 0.5, 0.89]))
    assert int(out.iterations) == BUDGET and not bool(out.solved)
    assert int(out.state.updates) == BUDGET
    np.testing.assert_array_equal(out.metrics.valid, np.ones(BUDGET, bool))
    np.testing.assert_allclose(out.metrics.entropy, 3.0 * np.arange(1, BUDGET + 1))


def test_a_non_finite_collection_makes_no_update_and_is_flagged():
    finite = np.ones(BUDGET, bool)
    finite[1] = False
    out = _run(script(np.zeros(BUDGET), finite=finite))
    np.testing.assert_array_equal(out.state.updated_at, finite)
    np.testing.assert_array_equal(out.metrics.nonfinite, 1.0 - finite)
    np.testing.assert_allclose(out.metrics.value_loss, 2.0 * np.arange(1, BUDGET + 1) * finite)
    assert int(out.state.collected) == BUDGET


def test_an_update_reporting_nonfinite_is_flagged():
    bad = np.zeros(BUDGET, bool)
    bad[2] = True
    out = _run(script(np.zeros(BUDGET), bad=bad))
    np.testing.assert_array_equal(out.metrics.nonfinite, bad.astype(np.float32))
    np.testing.assert_array_equal(out.state.updated_at, np.ones(BUDGET, bool))


def test_without_stopping_it_runs_the_budget_and_keeps_updating():
    curve = [0.1, 0.95, 0.2, 1.0, 0.3, 0.0]
    out = _run(script(curve), stop_at_threshold=False)
    np.testing.assert_array_equal(out.metrics.valid, np.ones(BUDGET, bool))
    np.testing.assert_array_equal(out.state.updated_at, np.ones(BUDGET, bool))
    assert int(out.iterations) == 2 and bool(out.solved)
    never = _run(script(np.zeros(BUDGET)), stop_at_threshold=False)
    assert int(never.iterations) == BUDGET and not bool(never.solved)


@pytest.mark.parametrize("curve, run_at_least, ran", [
    ([0.1, 0.95, 0.2, 0.3, 0.4, 0.5], 4, 4),  # solved at 2, run to 4
    ([0.1, 0.2, 0.3, 0.4, 0.95, 0.5], 2, 5),  # solved at 5, past 2
    ([0.1, 0.2, 0.3, 0.4, 0.5, 0.6], 2, BUDGET),  # never solved
])
def test_run_at_least_stops_after_the_first_success_and_that_many(curve, run_at_least, ran):
    out = _run(script(curve), stop_at_threshold=False, run_at_least=run_at_least)
    assert _rows_ran(out) == ran and int(out.state.updates) == ran
    full = _run(script(curve), stop_at_threshold=False)
    assert int(out.iterations) == int(full.iterations) and bool(out.solved) == bool(full.solved)
    for short, whole in zip(out.metrics, full.metrics):  # the rows run are those of the full run
        np.testing.assert_array_equal(np.asarray(short)[:ran], np.asarray(whole)[:ran])
        np.testing.assert_array_equal(np.asarray(short)[ran:], 0)


@pytest.mark.parametrize("collect_keys", [1, 3])
def test_keys_are_splits_of_the_carry_key(collect_keys):
    out = _run(script(np.zeros(BUDGET)), collect_keys=collect_keys)
    rng = jax.random.PRNGKey(0)
    for it in range(BUDGET):
        keys = jax.random.split(rng, 2 + collect_keys)
        np.testing.assert_array_equal(out.aux.collect_keys[it], keys[1:-1])
        np.testing.assert_array_equal(out.state.update_keys[it], keys[-1])
        rng = keys[0]
    np.testing.assert_array_equal(out.rng, rng)


def test_progress_reports_every_iteration_one_based():
    seen = []

    def run(s, rng):
        collect, update = _fakes(s)
        learner, aux = _start(1)
        return rl_loop.iterate(collect, update, learner, rng, threshold=THRESHOLD, budget=BUDGET, aux=aux,
                               progress_fn=progress.host(seen.append))

    curve = [0.1, 0.5, 0.95, 0.0, 0.0, 0.0]
    out = jax.block_until_ready(jax.jit(run)(script(curve), jax.random.PRNGKey(0)))
    jax.effects_barrier()
    assert [m["phase"] for m in seen] == [progress.ITERATION] * 3
    seen.sort(key=lambda m: int(m["iteration"]))
    assert [int(m["iteration"]) for m in seen] == [1, 2, 3] == list(range(1, int(out.iterations) + 1))
    np.testing.assert_allclose([float(m["success_rate"]) for m in seen], curve[:3])
    np.testing.assert_allclose([float(m["mean_return"]) for m in seen], [0, -1, -2])


def test_mean_terms_are_numpy_means_over_the_steps():
    per_step = rl_loop.UpdateTerms(*np.random.default_rng(0).normal(size=(5, 7)).astype(np.float32))
    means = rl_loop.mean_terms(per_step)
    for got, steps in zip(means, per_step):
        chex.assert_shape(got, ())
        np.testing.assert_allclose(got, np.mean(steps), rtol=1e-6, atol=1e-7)
    chex.assert_trees_all_equal(rl_loop.zero_terms(), rl_loop.UpdateTerms(*(jnp.float32(0),) * 4, jnp.float32(np.nan)))


@pytest.mark.parametrize("curve, cap, expected", [
    ([0.1, 0.95, 0.2], 3, (2, True)),
    ([0.9, 0.0], 2, (1, True)),  # at the threshold counts
    ([0.1, 0.2, 0.89], 3, (3, False)),
    ([0.1, 0.2], 10, (10, False)),  # the cap, not the curve's length
    ([0.0, 0.0, 1.0, 1.0], 4, (3, True)),
])
def test_first_success_on_hand_made_curves(curve, cap, expected):
    iterations, solved = rl_loop.first_success(jnp.asarray(curve, jnp.float32), THRESHOLD, cap)
    assert (int(iterations), bool(solved)) == expected
    assert iterations.dtype == jnp.int32


def test_empty_metrics_are_zeros_not_run():
    metrics = rl_loop.empty_metrics(BUDGET)
    for field in metrics:
        chex.assert_shape(field, (BUDGET,))
        np.testing.assert_array_equal(field, 0)
    assert metrics.valid.dtype == jnp.bool_


def test_under_vmap_a_stopped_members_rollouts_are_marked_inactive_and_its_progress_dropped():
    """A vmapped loop runs the body for every member until all have stopped: collections traced inside see the
    member's loop condition (``acting.only_if``: host-simulated rollouts skip the stopped members) and the
    stopped members' progress calls are dropped."""
    actives, seen = [], []

    def run(s, rng):
        collect, update = _fakes(s)

        def watching(learner, aux, keys, it):  # what a rollout traced here would be told
            jax.debug.callback(lambda a, i, n: actives.append((int(n), int(i), bool(a))),
                               acting._active_stack()[-1], it, learner.collected)
            return collect(learner, aux, keys, it)

        learner, aux = _start(1)
        out = rl_loop.iterate(watching, update, learner, rng, threshold=THRESHOLD, budget=BUDGET, aux=aux,
                              progress_fn=progress.host(seen.append))
        return out.iterations

    curves = jnp.asarray([[0.95, 0, 0, 0, 0, 0], [0.1, 0.2, 0.95, 0, 0, 0]], jnp.float32)  # stop after 1 and 3
    s = jax.vmap(script)(curves)
    iterations = jax.block_until_ready(jax.jit(jax.vmap(run, (0, None)))(s, jax.random.PRNGKey(0)))
    jax.effects_barrier()
    np.testing.assert_array_equal(iterations, [1, 3])
    assert not acting._active_stack()  # the context is left as found
    # (collections made, iteration, active): three bodies ran for both members; member 0, stopped after its
    # first, ran the last two from its final carry, inactive
    assert sorted(actives) == [(0, 0, True), (0, 0, True), (1, 1, False), (1, 1, False), (1, 1, True),
                               (2, 2, True)]
    assert sorted((round(float(m["success_rate"]), 2), int(m["iteration"])) for m in seen) == [
        (0.1, 1), (0.2, 2), (0.95, 1), (0.95, 3)]
    assert all("active" not in m for m in seen)
