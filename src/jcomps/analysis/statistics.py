"""The statistics of a run's results, as pure functions of numpy arrays: means with standard errors, backward
transfer, the significance of a difference between methods (t-test and bootstrap), the interquartile mean with its
stratified-bootstrap interval, and the arithmetic behind the continual-RL field's summaries (built on
``jcomps.analysis.continual_metrics``). ``jcomps.analysis.report`` applies them to a run directory and writes what they
return.

Arrays are seeds × tasks ``[S, N]`` (task = position in the sequence) unless said otherwise; per-iteration arrays
are ``[S, N, budget]`` masked by a ``valid`` of the same shape. NaN marks what is undefined.
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import numpy as np

from jcomps.analysis import continual_metrics as cm

BOOTSTRAP_SAMPLES = 30_000
"""Resamples of the bootstrap significance test (``significance``)."""
IQM_BOOTSTRAP_SAMPLES = 2_000
"""Resamples of the IQM's stratified-bootstrap interval (``iqm_ci``)."""
FT_REFERENCE = "ppo"
"""The reference of forward transfer: PPO from scratch on every task (Continual World's single-task reference)."""


def mean_se(x: np.ndarray, axis=0):
    """Mean and standard error over ``axis``, ignoring NaN (NaN where nothing is finite, SE 0 for one value): two
    f64 arrays of ``x``'s shape without ``axis``."""
    x = np.asarray(x, np.float64)
    n = np.sum(np.isfinite(x), axis=axis)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = np.nanmean(x, axis=axis)
        sd = np.nanstd(x, axis=axis, ddof=1)
    return mean, np.where(n > 1, sd / np.sqrt(np.maximum(n, 1)), np.where(n == 1, 0.0, np.nan))


def nanmean(x: np.ndarray, axis=None) -> np.ndarray:
    """``np.nanmean`` without its warning for an all-NaN slice (whose mean is NaN, as it should be)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(x, axis=axis)


def per_task_mean(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """[S, N]: the mean of ``values`` [S, N, budget] over the iterations that ran (``valid``; 0 for a task with
    none)."""
    return np.where(valid, values, 0).sum(-1) / np.maximum(valid.sum(-1), 1)


def backward_transfer(returns: np.ndarray, valid: np.ndarray, backward_returns: np.ndarray,
                      backward_valid: np.ndarray) -> np.ndarray:
    """f64[S, N]: normalized reward on the previous k tasks after each task (NaN where undefined): (c − a)/(b − a)
    with a, b, c averaged over the previous tasks j evaluated, a the return of task j's first iteration, b of its
    last, c of the policy after task i on task j.

    Args:
      returns: [S, N, budget], the mean return of every iteration of each task's RL step (masked by ``valid``).
      valid: bool[S, N, budget].
      backward_returns: [S, N, k], the policy after task i on task i − 1 − d.
      backward_valid: bool[S, N, k].
    """
    seeds, tasks = returns.shape[:2]
    first = returns[:, :, 0]
    last = np.take_along_axis(returns, np.maximum(valid.sum(-1) - 1, 0)[..., None], axis=2)[..., 0]
    c, ok = backward_returns, backward_valid
    out = np.full((seeds, tasks), np.nan)
    for s in range(seeds):
        for i in range(tasks):
            prev = [i - 1 - d for d in range(ok.shape[2]) if ok[s, i, d]]
            if not prev:
                continue
            a, b = first[s, prev].mean(), last[s, prev].mean()
            cc = c[s, i][ok[s, i]].mean()
            if abs(b - a) > 1e-8:
                out[s, i] = (cc - a) / (b - a)
    return out


def _t_statistic(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Student's two-sample t (pooled variance) along the last axis: x [..., n], y [..., m] -> [...]."""
    nx, ny = x.shape[-1], y.shape[-1]
    vx, vy = x.var(-1, ddof=1), y.var(-1, ddof=1)
    pooled = ((nx - 1) * vx + (ny - 1) * vy) / (nx + ny - 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        return (x.mean(-1) - y.mean(-1)) / np.sqrt(pooled * (1 / nx + 1 / ny))


def significance(x, y, samples: int = BOOTSTRAP_SAMPLES, seed: int = 0) -> dict:
    """Two-sided independent t-test of x [n] against y [m], analytic and by bootstrap under the null of equal
    means (Efron & Tibshirani 16.4): {"mean_a", "mean_b", "n_a", "n_b", "t", "p_ttest", "p_bootstrap",
    "bootstrap_samples"}, the test's values None with fewer than two values in a group."""
    from scipy import stats

    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    out = {"mean_a": float(x.mean()), "mean_b": float(y.mean()), "n_a": len(x), "n_b": len(y),
           "t": None, "p_ttest": None, "p_bootstrap": None, "bootstrap_samples": samples}
    if len(x) < 2 or len(y) < 2:
        return out
    t = float(_t_statistic(x, y))
    if not np.isfinite(t):  # both groups constant
        same = bool(x.mean() == y.mean())
        out.update(t=None, p_ttest=1.0 if same else 0.0, p_bootstrap=1.0 if same else 0.0)
        return out
    out["t"] = t
    out["p_ttest"] = float(stats.ttest_ind(x, y).pvalue)
    pooled = np.concatenate([x, y]).mean()
    x0, y0 = x - x.mean() + pooled, y - y.mean() + pooled
    rng = np.random.default_rng(seed)
    tb = _t_statistic(x0[rng.integers(0, len(x), (samples, len(x)))], y0[rng.integers(0, len(y), (samples, len(y)))])
    # A resample whose groups are both constant has t = ±inf when their means differ (as extreme as it gets: it
    # counts) and NaN when they are equal (t = 0).
    tb = np.where(np.isnan(tb), 0.0, tb)
    out["p_bootstrap"] = float((np.sum(np.abs(tb) >= abs(t)) + 1) / (samples + 1))
    return out


def iqm(scores: np.ndarray) -> float:
    """Interquartile mean of all entries of ``scores`` (any shape): the mean of the middle 50% (scipy's
    ``trim_mean`` cutting 25% at each end, rliable's ``aggregate_iqm``)."""
    from scipy import stats

    return float(stats.trim_mean(np.asarray(scores, np.float64).reshape(-1), 0.25))


def iqm_ci(scores: np.ndarray, samples: int = IQM_BOOTSTRAP_SAMPLES, seed: int = 0, level: float = 0.95) -> dict:
    """IQM of ``scores`` (f[seeds, tasks]) with a stratified-bootstrap percentile confidence interval: each resample
    draws, for every task independently, as many seeds as there are with replacement (rliable's
    ``StratifiedBootstrap``). {"iqm", "ci": [low, high] (None with one seed), "level", "bootstrap_samples",
    "seeds", "num_tasks"}."""
    x = np.asarray(scores, np.float64)
    n, tasks = x.shape
    out = {"iqm": iqm(x), "ci": [None, None], "level": level, "bootstrap_samples": samples, "seeds": n,
           "num_tasks": tasks}
    if n < 2:
        return out
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, n, (samples, n, tasks))
    from scipy import stats

    resampled = np.take_along_axis(np.broadcast_to(x, (samples, n, tasks)), idx, axis=1).reshape(samples, -1)
    values = stats.trim_mean(resampled, 0.25, axis=1)
    lo, hi = np.percentile(values, [50 * (1 - level), 50 * (1 + level)])
    out["ci"] = [float(lo), float(hi)]
    return out


def sequence_halves(num_tasks: int) -> list[tuple[int, int]]:
    """(first, last) 1-based task ranges of the two halves of a sequence (the second holds the odd task)."""
    half = num_tasks // 2
    return [(1, half), (half + 1, num_tasks)] if half >= 1 else [(1, num_tasks)]


def profile_taus(horizon: int, points: int = 100) -> np.ndarray:
    """i64[≤ points]: the τ grid of the performance profiles, at most ``points`` integers from 1 to ``horizon``,
    both included."""
    return np.unique(np.linspace(1, horizon, min(horizon, points)).round().astype(np.int64))


def probability_of_fewer_iterations(iterations: np.ndarray, baseline_iterations: np.ndarray) -> dict:
    """rliable's probability that a run needs fewer iterations-to-success (``iterations`` [S, N]) than a run of
    the baseline (``baseline_iterations`` [S', N]) on the same task, ties counting one half, averaged over tasks,
    with a 95% stratified-bootstrap interval (``continual_metrics.probability_of_improvement_ci``)."""
    return cm.probability_of_improvement_ci(-iterations.astype(np.float64), -baseline_iterations.astype(np.float64))


class Learnt(NamedTuple):
    """Forgetting and average performance from the evaluations of the learnt tasks at P' evaluations.

    Attributes:
      forgetting: f64[S, N] at the last evaluation, NaN where a task was not evaluated both times.
      forgetting_per_seed: f64[S], each seed's mean of ``forgetting`` over the tasks.
      forgetting_by_evaluation: P' arrays f64[S], each seed's mean forgetting over the tasks at each evaluation.
      performance_per_seed: f64[S], each seed's mean success over the tasks learnt, at the last evaluation.
      performance_by_evaluation: P' arrays f64[S], the same at each evaluation.
    """

    forgetting: np.ndarray
    forgetting_per_seed: np.ndarray
    forgetting_by_evaluation: list
    performance_per_seed: np.ndarray
    performance_by_evaluation: list


def learnt(success_when_learnt: np.ndarray, valid_when_learnt: np.ndarray, later_success: np.ndarray,
           later_valid: np.ndarray, rows: list[int]) -> Learnt:
    """Continual World's forgetting and average performance (``continual_metrics``) at the evaluations ``rows``.

    Args:
      success_when_learnt: [S, N], the success on task i right after it was learnt.
      valid_when_learnt: bool[S, N].
      later_success: [S, P, N], the success on every task learnt by each evaluation.
      later_valid: bool[S, P, N].
      rows: the evaluations (indices into P) to measure at, the last of them the final one.
    """
    def forgetting_at(p):
        return cm.forgetting(success_when_learnt, later_success[:, p], valid_when_learnt & later_valid[:, p])

    def performance_at(p):
        return cm.average_performance(later_success[:, p], later_valid[:, p])

    final = rows[-1]
    f = forgetting_at(final)
    return Learnt(f, nanmean(f, axis=1), [nanmean(forgetting_at(p), axis=1) for p in rows], performance_at(final),
                  [performance_at(p) for p in rows])


def forward_transfer(success_rate: np.ndarray, valid: np.ndarray, reference_success_rate: np.ndarray,
                     reference_valid: np.ndarray, ids: np.ndarray, horizon: int) -> tuple:
    """Continual World's forward transfer against a reference (PPO from scratch): (AUC f64[S, N], AUC_ref f64[S, N],
    FT f64[S, N]) with FT = (AUC − AUC_ref)/(1 − AUC_ref), AUC the success rate averaged over ``horizon``
    iterations (``continual_metrics.auc``), AUC_ref the reference's averaged over its seeds on the same task.

    Args:
      success_rate: [S, N, budget], the success rate of every iteration of each task's RL step.
      valid: bool[S, N, budget].
      reference_success_rate: [S, N', budget'], the reference's (N' ≤ ``ids``' tasks).
      reference_valid: bool[S, N', budget'].
      ids: [S, ≥ max(N, N')], each seed's task values (the reference is matched by task, not position).
      horizon: iterations the AUCs average over (≥ every budget).
    """
    n = valid.shape[1]
    a = cm.auc(success_rate, valid, horizon)
    ref_a = cm.reference_by_task(cm.auc(reference_success_rate, reference_valid, horizon),
                                 ids[:, :reference_valid.shape[1]], ids[:, :n])
    return a, ref_a, cm.forward_transfer(a, ref_a)


class CriticFit(NamedTuple):
    """How well an RL step's critic fitted its value targets, per seed and task [S, N] (NaN where not measured:
    no iteration updated, or the method reports no explained variance).

    Attributes:
      ev_mean: the explained variance of the targets, mean over the task's iterations that updated.
      ev_first, ev_last: at the task's first and last iteration that updated.
      value_loss: the value loss, mean over the same iterations.
    """

    ev_mean: np.ndarray
    ev_first: np.ndarray
    ev_last: np.ndarray
    value_loss: np.ndarray


def critic_fit(value_ev, value_loss, valid) -> CriticFit:
    """``CriticFit`` from per-iteration ``value_ev``, ``value_loss`` and ``valid`` [S, N, budget]: an iteration
    counts where it ran and measured the fit (a finite ``value_ev``; the iteration that reached the threshold made
    no update and measured none)."""
    ev = np.asarray(value_ev, np.float64)
    measured = np.asarray(valid, bool) & np.isfinite(ev)
    any_ = measured.any(-1)
    first = np.argmax(measured, axis=-1)
    last = ev.shape[-1] - 1 - np.argmax(measured[..., ::-1], axis=-1)
    pick = lambda i: np.where(any_, np.take_along_axis(ev, i[..., None], -1)[..., 0], np.nan)  # noqa: E731
    loss = np.where(measured, np.asarray(value_loss, np.float64), np.nan)
    return CriticFit(cm.nanmean(np.where(measured, ev, np.nan), -1), pick(first), pick(last), cm.nanmean(loss, -1))
