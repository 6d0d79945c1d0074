"""Tests of the continual-RL field's metrics (``jcomps.analysis.continual_metrics``): their laws and hand-computed
cases."""

import numpy as np
import pytest
from scipy import stats

from jcomps.analysis import continual_metrics as cm


def test_a_policy_that_never_changes_has_zero_forgetting():
    rng = np.random.default_rng(0)
    success = rng.uniform(0.0, 1.0, (3, 5))
    valid = np.ones((3, 5), bool)
    valid[:, 4] = False  # not evaluated later: undefined, not zero
    f = cm.forgetting(success, success, valid)
    np.testing.assert_array_equal(f[:, :4], 0.0)
    assert np.all(np.isnan(f[:, 4]))
    # Hand case: 0.9 when learnt, 0.6 at the end: 0.3 forgotten; a task that improved later has negative forgetting.
    np.testing.assert_allclose(cm.forgetting([[0.9, 0.2]], [[0.6, 0.5]], [[True, True]]), [[0.3, -0.3]])
    with pytest.raises(ValueError, match="forgetting: shapes differ"):
        cm.forgetting(success, success[:, :2], valid)


def test_average_performance_is_the_mean_over_the_tasks_evaluated():
    success = np.array([[1.0, 0.5, 0.7], [0.0, 0.0, 0.9]])
    valid = np.array([[True, True, False], [True, False, False]])
    np.testing.assert_allclose(cm.average_performance(success, valid), [0.75, 0.0])
    assert np.isnan(cm.average_performance(success, np.zeros_like(valid))).all()


def test_auc_carries_the_last_success_past_an_early_stop():
    # One seed, two tasks, budget 4: the first stopped at its 3rd iteration, the second used the whole budget.
    success = np.array([[[0.0, 0.5, 0.8, 0.0], [0.1, 0.2, 0.3, 0.4]]])
    valid = np.array([[[True, True, True, False], [True, True, True, True]]])
    np.testing.assert_allclose(cm.auc(success, valid, 4), [[(0.0 + 0.5 + 0.8 + 0.8) / 4, 0.25]])
    np.testing.assert_allclose(cm.auc(success, valid, 6), [[(1.3 + 3 * 0.8) / 6, (1.0 + 2 * 0.4) / 6]])
    with pytest.raises(ValueError, match="horizon=3"):
        cm.auc(success, valid, 3)


def test_forward_transfer_of_the_reference_against_itself_is_zero():
    rng = np.random.default_rng(1)
    auc = rng.uniform(0.0, 0.99, (4, 6))
    np.testing.assert_array_equal(cm.forward_transfer(auc, auc), 0.0)
    # Hand cases: half of what was left to learn, everything, worse than the reference; a reference at 1 leaves
    # nothing to transfer.
    np.testing.assert_allclose(cm.forward_transfer([0.6, 1.0, 0.1, 0.7], [0.2, 0.2, 0.2, 1.0]),
                               [0.5, 1.0, -0.125, np.nan])


def test_the_reference_is_matched_by_task_not_position():
    # Two seeds with shuffled orders of tasks 10, 20, 30: the reference's AUC of a task is its mean over the seeds
    # wherever it sat.
    ref = np.array([[0.1, 0.2, 0.3], [0.5, 0.4, 0.9]])
    ref_ids = np.array([[10, 20, 30], [30, 20, 10]])
    got = cm.reference_by_task(ref, ref_ids, np.array([[20, 10, 30], [10, 30, 40]]))
    np.testing.assert_allclose(got, [[0.3, 0.5, 0.4], [0.5, 0.4, np.nan]])  # 20: (0.2+0.4)/2, 10: (0.1+0.9)/2


def test_probability_of_improvement_laws_and_mann_whitney():
    rng = np.random.default_rng(2)
    x = rng.integers(1, 20, (5, 4)).astype(float)  # ties likely
    assert cm.probability_of_improvement(x, x) == 0.5
    y = rng.integers(1, 20, (7, 4)).astype(float)
    assert cm.probability_of_improvement(x, y) + cm.probability_of_improvement(y, x) == pytest.approx(1.0)
    # Per task the Mann-Whitney U of x against y over the pairs, averaged over tasks.
    u = np.mean([stats.mannwhitneyu(x[:, t], y[:, t]).statistic / (5 * 7) for t in range(4)])
    assert cm.probability_of_improvement(x, y) == pytest.approx(u)
    # Hand case, one task: pairs (3,1) > , (3,3) tie, (4,1) >, (4,3) >: 3.5 of 4.
    assert cm.probability_of_improvement([[3.0], [4.0]], [[1.0], [3.0]]) == 0.875
    with pytest.raises(ValueError, match="same tasks"):
        cm.probability_of_improvement(x, y[:, :3])


def test_probability_of_improvement_interval():
    rng = np.random.default_rng(3)
    x, y = rng.normal(1.0, 1.0, (6, 5)), rng.normal(0.0, 1.0, (6, 5))
    out = cm.probability_of_improvement_ci(x, y, samples=600)
    assert out["ci"][0] < out["probability"] < out["ci"][1] and out["probability"] > 0.5
    # Seeds are resampled within each task: a method better than the other on every pair stays so in every resample.
    assert cm.probability_of_improvement_ci(x + 10.0, x, samples=200)["ci"] == [1.0, 1.0]
    same = np.tile(np.arange(5.0), (4, 1))  # every seed equal on each task: every resample is the data
    assert cm.probability_of_improvement_ci(same, same, samples=200)["ci"] == [0.5, 0.5]


def test_performance_profile_counts_solved_runs_within_tau():
    its = np.array([[1, 3, 5], [2, 5, 5]])
    solved = np.array([[True, True, True], [True, True, False]])  # the last ran out of its budget of 5
    np.testing.assert_allclose(cm.performance_profile(its, solved, [1, 2, 3, 4, 5]),
                               [1 / 6, 2 / 6, 3 / 6, 3 / 6, 5 / 6])
    out = cm.performance_profile_ci(its, solved, np.arange(1, 6), samples=300)
    assert out["fraction"] == pytest.approx([1 / 6, 2 / 6, 3 / 6, 3 / 6, 5 / 6], abs=1e-6)  # rounded for JSON
    assert all(lo <= f <= hi for lo, f, hi in zip(out["ci_low"], out["fraction"], out["ci_high"]))
    # Task 1 is solved at iteration 1 or 2 by every seed: the band at tau 1 is [0, 1/3], from resamples of it.
    assert out["ci_low"][0] == 0.0 and out["ci_high"][0] == pytest.approx(1 / 3, abs=1e-6)
