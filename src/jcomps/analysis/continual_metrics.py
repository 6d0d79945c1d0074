"""The continual-RL field's metrics, as pure functions of arrays: Continual World's forgetting, forward transfer and
average performance (Wołczyk et al. 2021), and rliable's probability of improvement and performance profiles
(Agarwal et al. 2021). ``jcomps.analysis.report`` applies them to a run's raw results; the choices behind them are in
docs/design.md ("The continual-RL field's metrics").

Arrays are seeds × tasks ``[S, N]`` (task = position in the sequence) unless said otherwise; NaN marks what is
undefined, and means skip it.
"""

from __future__ import annotations

import warnings

import numpy as np

BOOTSTRAP_SAMPLES = 2_000


def nanmean(x, axis=None):
    """``np.nanmean`` without the warning where a slice is all NaN (that slice's mean is NaN)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN slice is NaN, as it should be
        return np.nanmean(x, axis=axis)


def forgetting(when_learnt, later, valid) -> np.ndarray:
    """F[s, i] = success on task i right after it was learnt − success on task i of a later policy (Continual
    World's F_i = p_i(i·Δ) − p_i(T) when the later policy is the final one): f64[S, N], NaN where ``valid``
    (bool[S, N]: both were evaluated) is False. Positive: forgotten; negative: improved by later tasks."""
    when_learnt, later = np.asarray(when_learnt, np.float64), np.asarray(later, np.float64)
    if when_learnt.shape != later.shape or np.shape(valid) != later.shape:
        raise ValueError(f"forgetting: shapes differ: when_learnt {when_learnt.shape}, later {later.shape}, valid "
                         f"{np.shape(valid)}")
    return np.where(valid, when_learnt - later, np.nan)


def average_performance(success, valid) -> np.ndarray:
    """f64[S]: each seed's mean success over the tasks evaluated (``valid`` bool[S, N]); Continual World's P(t)
    at the time of the evaluation. NaN for a seed with none."""
    return nanmean(np.where(valid, np.asarray(success, np.float64), np.nan), axis=-1)


def auc(success_rate, valid, horizon: int) -> np.ndarray:
    """f64[S, N]: the mean success rate of each task's RL step over ``horizon`` iterations.

    ``success_rate`` and ``valid`` are [S, N, budget] (``TaskMetrics.per_iteration``): the iterations that ran,
    from the first, until the threshold or the budget. A step that stopped early hands on the policy that reached
    the threshold, so its last success rate is carried to the horizon; comparing methods over the same horizon
    then rewards reaching the threshold sooner, as Continual World's area under the curve over a fixed number of
    steps does. A task with no iteration is NaN."""
    success_rate, valid = np.asarray(success_rate, np.float64), np.asarray(valid, bool)
    ran = valid.sum(-1)
    if horizon < 1 or np.any(ran > horizon):
        raise ValueError(f"auc: horizon={horizon} must be >= 1 and >= every task's iterations (up to {ran.max()})")
    last = np.take_along_axis(success_rate, np.maximum(ran - 1, 0)[..., None], axis=-1)[..., 0]
    total = np.where(valid, success_rate, 0.0).sum(-1) + (horizon - ran) * last
    return np.where(ran > 0, total / horizon, np.nan)


def reference_by_task(reference, reference_ids, ids) -> np.ndarray:
    """f64[S, N]: for every (seed, position) of a method whose task there is ``ids[s, i]``, the mean of the
    reference's ``reference`` [S', N'] over every (seed, position) that held the same task (``reference_ids``):
    the reference matched by task, not position (stationary sequences shuffle the order per seed). NaN where the
    reference never learnt that task or its values are all NaN."""
    reference = np.asarray(reference, np.float64)
    reference_ids, ids = np.asarray(reference_ids), np.asarray(ids)
    if reference_ids.shape != reference.shape:
        raise ValueError(f"reference_by_task: reference {reference.shape} and reference_ids {reference_ids.shape} "
                         "differ")
    out = np.full(ids.shape, np.nan)
    for task in np.unique(ids):
        held = reference_ids == task
        if held.any():
            out[ids == task] = nanmean(reference[held])
    return out


def forward_transfer(auc_, reference_auc) -> np.ndarray:
    """Continual World's forward transfer FT = (AUC − AUC_ref)/(1 − AUC_ref), elementwise: 1 when the method
    succeeds from its first iteration, 0 when it does as well as the reference, negative when worse. NaN where the
    reference is NaN or already at 1 (nothing left to transfer)."""
    a, r = np.asarray(auc_, np.float64), np.asarray(reference_auc, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(r < 1.0, (a - r) / (1.0 - r), np.nan)


def probability_of_improvement(x, y) -> float:
    """rliable's P(X > Y): for each task, the probability that a run of X scores higher than a run of Y (the
    Mann–Whitney U statistic over all pairs of X's and Y's seeds divided by their number, ties counting one half),
    averaged over tasks. ``x`` f[n, T], ``y`` f[m, T]: seeds × tasks, higher is better (pass −iterations for
    iterations-to-success). 0.5 for identical groups; P(X > Y) + P(Y > X) = 1."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    return float(_poi(x[None], y[None])[0])


def _poi(x, y):
    """P(X > Y) for a batch: x f[B, n, T], y f[B, m, T] -> f[B]."""
    if x.ndim != 3 or y.ndim != 3 or x.shape[2] != y.shape[2] or 0 in x.shape[1:] or 0 in y.shape[1:]:
        raise ValueError(f"probability_of_improvement: expected seeds × tasks with the same tasks, got {x.shape[1:]} "
                         f"and {y.shape[1:]}")
    gt = (x[:, :, None, :] > y[:, None, :, :]).mean((1, 2))
    eq = (x[:, :, None, :] == y[:, None, :, :]).mean((1, 2))
    return (gt + 0.5 * eq).mean(-1)


def _stratified(rng, n: int, tasks: int, samples: int) -> np.ndarray:
    """Resampled seed indices [samples, n, tasks]: for every task independently, n seeds drawn with replacement."""
    return rng.integers(0, n, (samples, n, tasks))


def _percentile_ci(values, level: float) -> list:
    lo, hi = np.percentile(values, [50 * (1 - level), 50 * (1 + level)], axis=0)
    return [lo, hi]


def probability_of_improvement_ci(x, y, samples: int = BOOTSTRAP_SAMPLES, seed: int = 0,
                                  level: float = 0.95) -> dict:
    """``probability_of_improvement(x, y)`` with a percentile confidence interval from a stratified bootstrap
    (rliable's ``StratifiedIndependentBootstrap``): each resample draws, for every task, X's seeds and Y's seeds
    independently with replacement."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    out = {"probability": probability_of_improvement(x, y), "ci": [None, None], "level": level,
           "bootstrap_samples": samples}
    rng = np.random.default_rng(seed)
    values = []
    for start in range(0, samples, 250):  # in batches: the pairwise comparison holds B × n × m × T booleans
        b = min(250, samples - start)
        ix, iy = _stratified(rng, x.shape[0], x.shape[1], b), _stratified(rng, y.shape[0], y.shape[1], b)
        values.append(_poi(np.take_along_axis(np.broadcast_to(x, ix.shape), ix, axis=1),
                           np.take_along_axis(np.broadcast_to(y, iy.shape), iy, axis=1)))
    lo, hi = _percentile_ci(np.concatenate(values), level)
    out["ci"] = [float(lo), float(hi)]
    return out


def performance_profile(iterations, solved, taus) -> np.ndarray:
    """f64[len(taus)]: the fraction of runs (seeds × tasks) that reached the threshold within τ iterations, for
    each τ of ``taus`` (rliable's performance profile for a score where lower is better: the distribution of
    iterations-to-success, unsolved runs never counted)."""
    its, ok = np.asarray(iterations), np.asarray(solved, bool)
    taus = np.asarray(taus)
    return ((its[..., None] <= taus) & ok[..., None]).reshape(-1, len(taus)).mean(0)


def performance_profile_ci(iterations, solved, taus, samples: int = BOOTSTRAP_SAMPLES, seed: int = 0,
                           level: float = 0.95) -> dict:
    """``performance_profile`` with pointwise percentile confidence bands from a stratified bootstrap (seeds
    resampled with replacement within each task): {"tau", "fraction", "ci_low", "ci_high", ...} as lists."""
    its, ok = np.asarray(iterations), np.asarray(solved, bool)
    taus = np.asarray(taus)
    reached = (its[..., None] <= taus) & ok[..., None]  # [S, N, taus]
    rng = np.random.default_rng(seed)
    idx = _stratified(rng, its.shape[0], its.shape[1], samples)
    counts = np.zeros((samples, len(taus)))
    for t in range(its.shape[1]):  # per task: [samples, S] seeds drawn, summed over them
        counts += reached[:, t][idx[:, :, t]].sum(1)
    lo, hi = _percentile_ci(counts / its.size, level)
    return {"tau": taus.tolist(), "fraction": performance_profile(its, ok, taus).round(6).tolist(),
            "ci_low": lo.round(6).tolist(), "ci_high": hi.round(6).tolist(), "level": level,
            "bootstrap_samples": samples}
