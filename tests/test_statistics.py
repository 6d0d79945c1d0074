"""Tests of the statistics of a run's results (``jcomps.analysis.statistics``): laws, invariants and hand-computed
cases."""

import subprocess
import sys

import numpy as np
import pytest
from scipy import stats

from jcomps.analysis import statistics


def test_the_module_is_pure():
    """Importing the statistics pulls in no plotting, no runner and no JAX."""
    code = ("import sys, jcomps.analysis.statistics; "
            "print(sorted(m for m in ('matplotlib', 'jax', 'jcomps.runner.experiment', 'jcomps.analysis.report', "
            "'jcomps.analysis.plots') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_mean_se_is_the_mean_and_the_standard_error_over_seeds():
    x = np.array([[1.0, 4.0, np.nan], [3.0, np.nan, np.nan], [8.0, 6.0, np.nan]])
    mean, se = statistics.mean_se(x)
    assert mean[0] == pytest.approx(4.0) and se[0] == pytest.approx(np.std([1.0, 3.0, 8.0], ddof=1) / np.sqrt(3))
    # NaN is skipped: one seed left has no spread; none left is undefined.
    assert mean[1] == pytest.approx(5.0) and se[1] == pytest.approx(np.std([4.0, 6.0], ddof=1) / np.sqrt(2))
    assert np.isnan(mean[2]) and np.isnan(se[2])
    one_mean, one_se = statistics.mean_se(np.array([[7.0, 2.0]]))
    np.testing.assert_array_equal(one_mean, [7.0, 2.0])
    np.testing.assert_array_equal(one_se, [0.0, 0.0])
    row_mean, _ = statistics.mean_se(x[:, :2], axis=1)
    np.testing.assert_allclose(row_mean, [2.5, 3.0, 7.0])


def test_per_task_mean_averages_the_iterations_that_ran():
    values = np.array([[[1.0, 3.0, 100.0], [5.0, 100.0, 100.0]]])
    valid = np.array([[[True, True, False], [False, False, False]]])
    np.testing.assert_allclose(statistics.per_task_mean(values, valid), [[2.0, 0.0]])


def _backward(returns, valid, c, ok):
    return statistics.backward_transfer(np.asarray(returns, np.float64), np.asarray(valid), np.asarray(c, np.float64),
                                        np.asarray(ok))


def test_backward_transfer_formula():
    # One seed, 3 tasks, budget 2: task j's first and last returns a_j, b_j; after task 2 the policy scores c.
    ret = [[[0.0, 10.0], [2.0, 6.0], [0.0, 0.0]]]
    valid = [[[True, True], [True, True], [True, False]]]
    c = [[[0.0, 0.0], [5.0, 0.0], [4.0, 5.0]]]
    ok = [[[False, False], [True, False], [True, True]]]
    bt = _backward(ret, valid, c, ok)
    assert np.isnan(bt[0, 0])
    assert bt[0, 1] == pytest.approx((5.0 - 0.0) / (10.0 - 0.0))
    # After task 3: previous tasks 2 (d=0, c=4) and 1 (d=1, c=5): a = (2+0)/2, b = (6+10)/2, c = 4.5.
    assert bt[0, 2] == pytest.approx((4.5 - 1.0) / (8.0 - 1.0))


@pytest.mark.parametrize("c,expected", [(10.0, 1.0), (12.0, 1.2), (0.0, 0.0), (-5.0, -0.5)])
def test_backward_transfer_is_1_when_nothing_is_forgotten_and_its_sign_says_which_way(c, expected):
    """Task 1 went from 0 to 10: a policy that still scores 10 keeps everything (1), one above it improved on it
    (> 1), one back at the first iteration's return forgot it all (0), one below that is worse than new (< 0)."""
    ret, valid = [[[0.0, 10.0], [3.0, 3.0]]], [[[True, True], [True, False]]]
    bt = _backward(ret, valid, [[[0.0], [c]]], [[[False], [True]]])
    assert bt[0, 1] == pytest.approx(expected)


def test_backward_transfer_is_undefined_when_the_task_was_not_learnt():
    ret, valid = [[[4.0, 4.0], [3.0, 3.0]]], [[[True, True], [True, True]]]  # first = last: nothing to normalize by
    assert np.isnan(_backward(ret, valid, [[[0.0], [1.0]]], [[[False], [True]]])).all()


def test_the_t_statistic_is_students():
    rng = np.random.default_rng(3)
    x, y = rng.normal(0.0, 1.0, 6), rng.normal(1.0, 2.0, 9)
    assert float(statistics._t_statistic(x, y)) == pytest.approx(stats.ttest_ind(x, y).statistic)


def test_significance_matches_the_t_test_and_detects_equal_groups():
    rng = np.random.default_rng(0)
    x, y = rng.normal(0.0, 1.0, 8), rng.normal(3.0, 1.0, 8)
    s = statistics.significance(x, y, samples=4000)
    assert s["p_ttest"] < 0.05 and abs(s["p_bootstrap"] - s["p_ttest"]) < 0.05
    assert s["mean_a"] == pytest.approx(x.mean()) and s["n_a"] == s["n_b"] == 8 and s["bootstrap_samples"] == 4000
    same = statistics.significance(x, x + 1e-12, samples=2000)
    assert same["p_ttest"] > 0.9 and same["p_bootstrap"] > 0.9
    # Two seeds each: a quarter of the resamples have both groups constant (t = ±inf), which are as extreme as
    # the data, not ignored; the bootstrap cannot then go below ~1/4.
    tiny = statistics.significance(np.array([49.0, 44.2]), np.array([54.0, 60.8]), samples=4000)
    assert tiny["p_bootstrap"] > 0.2


def test_significance_of_constant_and_single_seed_groups():
    equal = statistics.significance([3.0, 3.0], [3.0, 3.0], samples=10)
    assert equal["t"] is None and equal["p_ttest"] == equal["p_bootstrap"] == 1.0
    apart = statistics.significance([3.0, 3.0], [5.0, 5.0], samples=10)
    assert apart["t"] is None and apart["p_ttest"] == apart["p_bootstrap"] == 0.0
    one = statistics.significance([3.0], [5.0, 6.0], samples=10)
    assert one["p_ttest"] is None and one["p_bootstrap"] is None and one["mean_b"] == 5.5


def test_significance_is_seeded():
    x, y = np.array([1.0, 2.0, 4.0]), np.array([2.0, 5.0, 7.0])
    assert statistics.significance(x, y, samples=500) == statistics.significance(x, y, samples=500)


def test_iqm_of_a_constant_is_the_constant_and_ignores_the_outer_quartiles():
    assert statistics.iqm(np.full((3, 4), 2.5)) == pytest.approx(2.5)
    x = np.arange(1.0, 9.0)  # 8 values: the middle 50% is 3, 4, 5, 6
    assert statistics.iqm(x) == pytest.approx(4.5)
    moved = x.copy()
    moved[[0, 1]], moved[[6, 7]] = -1e9, 1e9
    assert statistics.iqm(moved) == pytest.approx(4.5)


def test_iqm_and_its_stratified_bootstrap_interval():
    rng = np.random.default_rng(0)
    scores = rng.normal(50.0, 10.0, (5, 4))
    q = statistics.iqm_ci(scores, samples=500)
    flat = np.sort(scores.reshape(-1))
    assert q["iqm"] == pytest.approx(flat[5:15].mean())  # the middle 50% of 20 values
    assert q["ci"][0] < q["iqm"] < q["ci"][1]
    assert (q["seeds"], q["num_tasks"], q["bootstrap_samples"], q["level"]) == (5, 4, 500, 0.95)
    # Outliers barely move the IQM (they move the mean).
    spiked = scores.copy()
    spiked[0, 0] = 1e6
    assert abs(statistics.iqm(spiked) - q["iqm"]) < 5.0
    # Seeds are resampled within each task: when every seed scores the same on a task, every resample is the same.
    same = np.tile(np.arange(4.0), (5, 1))
    assert statistics.iqm_ci(same, samples=200)["ci"] == [pytest.approx(1.5)] * 2


def test_the_iqm_interval_narrows_with_more_seeds_and_needs_two():
    rng = np.random.default_rng(1)
    few, many = rng.normal(0.0, 1.0, (4, 3)), rng.normal(0.0, 1.0, (64, 3))
    width = lambda q: q["ci"][1] - q["ci"][0]  # noqa: E731
    assert width(statistics.iqm_ci(many, samples=300)) < width(statistics.iqm_ci(few, samples=300))
    assert statistics.iqm_ci(few[:1], samples=300)["ci"] == [None, None]


def test_sequence_halves_cover_the_sequence():
    assert statistics.sequence_halves(6) == [(1, 3), (4, 6)] and statistics.sequence_halves(5) == [(1, 2), (3, 5)]
    assert statistics.sequence_halves(1) == [(1, 1)]


@pytest.mark.parametrize("horizon", [1, 3, 100, 101, 1000])
def test_profile_taus_are_at_most_points_integers_from_1_to_the_horizon(horizon):
    taus = statistics.profile_taus(horizon)
    assert taus[0] == 1 and taus[-1] == horizon and len(taus) <= 100 and np.all(np.diff(taus) > 0)
    assert taus.dtype == np.int64
    if horizon <= 100:
        np.testing.assert_array_equal(taus, np.arange(1, horizon + 1))


def test_probability_of_fewer_iterations():
    its = np.array([[2, 5], [3, 4]])
    assert statistics.probability_of_fewer_iterations(its, its)["probability"] == 0.5
    assert statistics.probability_of_fewer_iterations(its, its + 10)["probability"] == 1.0
    worse = statistics.probability_of_fewer_iterations(its + 10, its)
    assert worse["probability"] == 0.0 and worse["ci"] == [0.0, 0.0]


def test_learnt_forgetting_and_average_performance():
    """Two seeds, two tasks, evaluations after task 1 and after task 2 (rows 0 and 1)."""
    when_learnt = np.array([[0.9, 0.8], [0.5, 1.0]])
    later = np.array([[[0.7, 0.0], [0.6, 0.8]], [[0.5, 0.0], [0.2, 1.0]]])  # [S, P, N]
    later_valid = np.array([[[True, False], [True, True]]] * 2)
    got = statistics.learnt(when_learnt, np.ones((2, 2), bool), later, later_valid, [0, 1])
    np.testing.assert_allclose(got.forgetting, [[0.3, 0.0], [0.3, 0.0]])
    np.testing.assert_allclose(got.forgetting_per_seed, [0.15, 0.15])
    np.testing.assert_allclose(got.forgetting_by_evaluation, [[0.2, 0.0], [0.15, 0.15]])
    np.testing.assert_allclose(got.performance_per_seed, [0.7, 0.6])
    np.testing.assert_allclose(got.performance_by_evaluation, [[0.7, 0.5], [0.7, 0.6]])
    # A policy that never changes forgets nothing.
    same = statistics.learnt(when_learnt, np.ones((2, 2), bool), np.stack([when_learnt] * 2, 1), later_valid, [1])
    np.testing.assert_array_equal(same.forgetting, 0.0)


def test_forward_transfer_against_itself_is_zero_and_against_a_weaker_reference_positive():
    success = np.array([[[0.0, 0.5, 1.0], [0.2, 0.4, 0.6]]])
    valid = np.ones_like(success, bool)
    ids = np.array([[10.0, 20.0]])
    a, ref_a, ft = statistics.forward_transfer(success, valid, success, valid, ids, 3)
    np.testing.assert_allclose(a, [[0.5, 0.4]])
    np.testing.assert_allclose(ref_a, a)
    np.testing.assert_allclose(ft, 0.0)
    _, _, better = statistics.forward_transfer(success, valid, np.zeros_like(success), valid, ids, 3)
    np.testing.assert_allclose(better, a)  # (AUC − 0)/(1 − 0)
