"""Results of a run directory: ``results.json``, the paper's plots and a significance table.

Everything here is computed from ``run.json`` and ``raw/<entry>.npz`` (``jcomps.runner.results.RawResults``), so
``python experiments/report.py RUN_DIR`` regenerates all of it at any time. This module reads the run directory,
builds ``results.json`` (``summarize``) and the markdown tables, and writes them; the arithmetic is in
``jcomps.analysis.statistics`` and the figures are drawn by ``jcomps.analysis.plots``.

Metrics (SPEC, "Metrics a user expects"):

- iterations-to-success per task (seeds × tasks), its mean ± standard error over seeds;
- the return and success-rate curves of every RL step, and the mean return per task;
- the lifelong return curve (every iteration of the sequence, task after task);
- backward transfer after task i: (c − a)/(b − a) with a, b, c averaged over the previous k tasks j: a the
  return of task j's first iteration, b of its last, c of the current policy evaluated on task j;
- held-out meta-test, measured at the start and after every chunk of tasks from the policy of that moment (no
  learning kept): iterations-to-success on each held-out task within a cap, and the mean return on the held-out
  tasks after a fixed number of PPO iterations (SPEC's "fixed small adaptation budget"; the paper gives none, L258);
- significance of a baseline method (``comps`` by default) against each other method on the per-seed mean
  iterations-to-success: a two-sided independent t-test, and the same test by bootstrap (30,000 resamples of the
  seeds under the null of equal means, Efron & Tibshirani 16.4);
- the field's current convention (Agarwal et al. 2021, "rliable"): the interquartile mean (IQM) of
  iterations-to-success over seeds × tasks, with a 95% percentile confidence interval from a stratified bootstrap
  (seeds resampled with replacement within each task, 2,000 resamples), for each half of the sequence;
- the continual-RL field's metrics (``jcomps.analysis.continual_metrics``; Continual World, Wołczyk et al. 2021, and
  rliable): forgetting per task (success right after learning it − success at the last evaluation of the learnt
  tasks, the end of the sequence) and at every evaluation; average performance (mean success over the tasks
  learnt); forward transfer against ``ppo`` from scratch when the run (or a merged run) has it, from the RL
  step's success curves; the probability that a method needs fewer iterations-to-success than the baseline on a
  task (Mann–Whitney over seeds, averaged over tasks) with a stratified-bootstrap interval; performance profiles
  of iterations-to-success (``plots/performance_profile.png``; the others in ``plots/continual_metrics.png``).

With a hyperparameter grid (``jcomps.runner.grid``) there is one entry per method and grid point, keyed
``METHOD[field=value,...]``, each with its ``grid`` values and an ``overall`` summary (mean iterations-to-success
over tasks and seeds ± the standard error of the per-seed means, mean return); ``best`` names each method's best
point (lowest mean iterations-to-success, ties broken by the higher mean return). The plots and the
significance table use each method's best point, and ``significance.md`` adds a table of every grid point.
"""

from __future__ import annotations

import os
from typing import Optional

import numpy as np

from jcomps import envs, methods
from jcomps.analysis import continual_metrics as cm
from jcomps.analysis import plots, statistics
from jcomps.analysis.statistics import BOOTSTRAP_SAMPLES, FT_REFERENCE, IQM_BOOTSTRAP_SAMPLES, mean_se
from jcomps.runner import grid as grids
from jcomps.runner import results as results_
from jcomps.runner import rundir
from jcomps.runner.description import RunDescription
from jcomps.runner.files import RunError, write_json
from jcomps.training import plasticity


def _curves(values: np.ndarray, valid: np.ndarray) -> list:
    """seeds × tasks × (valid iterations) nested lists."""
    return [[values[s, t][valid[s, t]].round(6).tolist() for t in range(values.shape[1])]
            for s in range(values.shape[0])]


def _json_float(x):
    return None if x is None or not np.isfinite(x) else float(x)


def _jsonable_value(v):
    return list(v) if isinstance(v, tuple) else v


def default_baseline(methods_run) -> Optional[str]:
    """The method the significance tables compare against by default: ``comps`` when it is in the run."""
    return "comps" if "comps" in methods_run else None


def check_baseline(baseline: Optional[str], methods_run) -> None:
    """ValueError naming ``--baseline`` unless it is None or one of the run's methods ``methods_run``."""
    if baseline is not None and baseline not in methods_run:
        raise ValueError(f"--baseline {baseline}: not a method of this run; its methods: {', '.join(methods_run)}")


def env_steps(description: RunDescription, method: str, values: Optional[dict]) -> tuple[int, int, int]:
    """Env steps one iteration of ``method`` collects in the run ``description`` (at grid point ``values``), those
    a solved task costs beyond its counted iterations (``Method.env_steps_per_task``) and those every task costs
    before its first iteration (``Method.env_steps_before_task``)."""
    built = methods.make(method, description.family, description.config(method, values))  # once: it holds all three
    return methods.base.env_steps_per_iteration(built), built.env_steps_per_task, built.env_steps_before_task


def summarize(description: RunDescription, raws: dict, baseline: Optional[str] = None) -> dict:
    """The content of ``results.json`` (``raws``: {entry key: RawResults}); the significance table compares
    ``baseline`` (a method of the run; default ``default_baseline``) with every other method."""
    run = description.run
    seeds = run.seed_list
    results = {"description": description.to_json(), "seeds": seeds, "methods": {}}
    entries = description.entries()
    overall_its, overall_ret = {}, {}
    # Every method's AUC over one horizon and performance profile over one τ grid: the longest budget of the run.
    horizon = max(raws[name].per_task.task.per_iteration.valid.shape[-1] for _, name, _ in entries)
    taus = statistics.profile_taus(horizon)
    for method, name, values in entries:
        results["methods"][name] = _entry(description, method, values, raws[name], taus)
        if values is not None:
            per_iteration = raws[name].per_task.task.per_iteration
            overall_its[name] = float(raws[name].per_task.task.iterations.mean())
            overall_ret[name] = float(statistics.per_task_mean(per_iteration.mean_return, per_iteration.valid).mean())
    best = {m: m for m in run.methods}
    if description.grid:
        best = grids.best(entries, overall_its, overall_ret)
        results["best"] = best
    baseline = baseline or default_baseline(run.methods)
    try:
        check_baseline(baseline, run.methods)
    except ValueError as err:
        raise RunError(str(err)) from None
    if baseline is not None:
        results["significance"] = _significance(raws, best, baseline, run.methods, bool(description.grid))
    reference = best.get(FT_REFERENCE)
    ids = np.stack([envs.sequence_values(description.family, run.sequence, s, run.num_tasks, run.tasks)
                    for s in seeds])
    for _, name, _ in entries:
        results["methods"][name]["forward_transfer"] = forward_transfer_summary(
            raws[name], None if reference is None else raws[reference], reference, ids, horizon)
    return results


def _entry(description: RunDescription, method: str, values, raw, taus) -> dict:
    """``results.json``'s summary of one entry (a method, or one grid point of it: ``values``) from its raw
    results; the forward transfer is added by ``summarize``, which needs every entry."""
    its = raw.per_task.task.iterations
    valid = raw.per_task.task.per_iteration.valid
    ret, succ = raw.per_task.task.per_iteration.mean_return, raw.per_task.task.per_iteration.success_rate
    per_task_return = statistics.per_task_mean(ret, valid)
    mean, se = mean_se(its)
    bt = statistics.backward_transfer(ret, valid, raw.per_task.backward_returns, raw.per_task.backward_valid)
    steps, task_steps, before_steps = env_steps(description, method, values)
    # Samples-to-success per seed and task: MAML+TL's iterations collect two batches, PPO's one; PNC's solved
    # tasks add their compress phase (an unsolved task's budget count includes it already); PEARL's every task
    # its initial prior-z collection.
    samples = its * steps + raw.per_task.task.solved * task_steps + before_steps
    samples_mean, samples_se = mean_se(samples)
    entry = {
        "iterations_to_success": its.astype(int).tolist(),
        "iterations_to_success_mean": mean.round(3).tolist(),
        "iterations_to_success_se": se.round(3).tolist(),
        "env_steps_per_iteration": int(steps),
        "env_steps_per_task": int(task_steps),
        "env_steps_before_task": int(before_steps),
        "env_steps_to_success": samples.astype(np.int64).tolist(),
        "env_steps_to_success_mean": samples_mean.round(1).tolist(),
        "env_steps_to_success_se": samples_se.round(1).tolist(),
        "solved": raw.per_task.task.solved.astype(bool).tolist(),
        "mean_return_per_task": per_task_return.round(6).tolist(),
        "return_curves": _curves(ret, valid),
        "success_rate_curves": _curves(succ, valid),
        "backward_transfer": [[_json_float(v) for v in row] for row in bt],
        "heldout": _heldout_summary(description, raw),
        "iqm": [{"tasks": list(r), **statistics.iqm_ci(its[:, r[0] - 1:r[1]])}
                for r in statistics.sequence_halves(its.shape[1])],
        "nonfinite_iterations": int(np.sum(raw.per_task.task.per_iteration.nonfinite > 0)),
        "seconds": float(raw.seconds),
        "devices": int(raw.devices),
    }
    entry["critic"] = critic_summary(raw.per_task.task.per_iteration)
    if raw.per_task.task.meta is not None:
        entry["meta"] = meta_summary(raw.per_task.task.meta)
    if raw.per_task.task.policy_health is not None:
        entry["policy"] = policy_summary(raw.per_task.task.policy_health)
    entry.update(learnt_summary(raw))
    entry["performance_profile"] = {"statistic": "fraction of runs (seeds × tasks) that reached the threshold "
                                                 "within tau iterations; 95% stratified-bootstrap band",
                                    **cm.performance_profile_ci(its, raw.per_task.task.solved, taus)}
    if values is not None:
        m_its, se_its = mean_se(its.astype(np.float64).mean(axis=1))
        entry.update({"method": method, "grid": {k: _jsonable_value(v) for k, v in values.items()},
                      "overall": {"iterations_to_success_mean": _json_float(m_its),
                                  "iterations_to_success_se": _json_float(se_its),
                                  "mean_return": _json_float(float(per_task_return.mean()))}})
    return entry


def _heldout_summary(description: RunDescription, raw) -> dict:
    """The held-out meta-test of one entry: zero-shot and adapted returns, iterations to success."""
    h_ret = raw.measured.heldout.mean_return.mean(axis=2)  # [seeds, points, iterations + 1], averaged over tasks
    return {
        "after_tasks": raw.heldout_after_tasks.tolist(),
        "zero_shot_return": h_ret[:, :, 0].round(6).tolist(),
        "adapted_return": h_ret[:, :, -1].round(6).tolist(),
        "adaptation_iterations": int(h_ret.shape[-1] - 1),
        # [seeds, points, held-out tasks]; the budget is the cap (never reached within it)
        "iterations_to_success": raw.measured.heldout.iterations.astype(int).tolist(),
        "iterations_to_success_mean": raw.measured.heldout.iterations.mean(axis=2).round(3).tolist(),
        "solved": raw.measured.heldout.solved.astype(bool).tolist(),
        "budget": int(description.eval.heldout_budget),  # resolved when the run was described or read
    }


def _significance(raws: dict, best: dict, baseline: str, method_names, grid: bool) -> dict:
    """The significance table: ``baseline`` against every other method, each at its best grid point."""
    base = raws[best[baseline]].per_task.task.iterations.mean(axis=1)
    others = [m for m in method_names if m != baseline]
    return {
        "baseline": best[baseline],
        "statistic": "per-seed mean iterations-to-success over the sequence"
                     + (", each method at its best grid point" if grid else ""),
        "against": {best[m]: statistics.significance(base, raws[best[m]].per_task.task.iterations.mean(axis=1))
                    for m in others},
        "probability_of_improvement": {best[m]: probability_of_improvement(raws[best[m]], raws[best[baseline]],
                                                                          best[baseline]) for m in others}}


def _rows(x, digits: int = 6):
    """A float array as nested lists, NaN as None."""
    x = np.asarray(x, np.float64)
    if x.ndim == 0:
        return _json_float(round(float(x), digits))
    return [_rows(v, digits) for v in x]


def _over_seeds(per_seed) -> dict:
    """{"mean", "se"} over seeds of a f[S] (NaN skipped)."""
    mean, se = mean_se(np.asarray(per_seed, np.float64))
    return {"mean": _json_float(mean), "se": _json_float(se)}


def learnt_summary(raw: results_.RawResults) -> dict:
    """Forgetting, average performance and the success matrix of one entry (Continual World's metrics) from the
    evaluations of its learnt tasks (``RawResults.learnt`` right after each task, ``learnt_tasks`` after each chunk
    or at the end): {"forgetting", "average_performance", "learnt_success"}, each with a ``note`` instead when the
    run has no such evaluations."""
    if raw.per_task.learnt is None or raw.measured.learnt is None:
        note = {"note": "not measured: the run was made before jcomps evaluated the learnt tasks"}
        return {"forgetting": note, "average_performance": note}
    learnt, later = raw.per_task.learnt, raw.measured.learnt
    rows = [p for p in range(later.valid.shape[1]) if later.valid[:, p].any()]
    if not rows:
        note = {"note": "not measured yet: the learnt tasks are evaluated at the end of the sequence only "
                        "(--learnt-eval end)"}
        return {"forgetting": note, "average_performance": note}
    after = [int(raw.heldout_after_tasks[p]) for p in rows]
    final = rows[-1]
    f, f_seed, f_by, p_seed, p_by = statistics.learnt(learnt.success_rate, learnt.valid, later.success_rate,
                                                      later.valid, rows)
    return {
        "forgetting": {
            "statistic": "per seed and task: success right after learning the task − success on it after "
                         f"{after[-1]} tasks (fresh episodes, the same ones both times); mean and s.e. over seeds of "
                         "each seed's mean over the tasks",
            "after_tasks": after[-1],
            "success_when_learnt": _rows(np.where(learnt.valid, learnt.success_rate, np.nan)),
            "final_success": _rows(np.where(later.valid[:, final], later.success_rate[:, final], np.nan)),
            "per_task": _rows(f),
            "per_task_mean": _rows(mean_se(f)[0]),
            **_over_seeds(f_seed),
            "by_evaluation": {"after_tasks": after, "mean": [_over_seeds(x)["mean"] for x in f_by],
                              "se": [_over_seeds(x)["se"] for x in f_by]},
        },
        "average_performance": {
            "statistic": f"per seed: mean success over the {after[-1]} tasks learnt, after the last of them; mean and "
                         "s.e. over seeds",
            "after_tasks": after[-1],
            "per_seed": _rows(p_seed),
            **_over_seeds(p_seed),
            "by_evaluation": {"after_tasks": after, "mean": [_over_seeds(x)["mean"] for x in p_by],
                              "se": [_over_seeds(x)["se"] for x in p_by]},
        },
        "learnt_success": {
            "statistic": "mean over seeds of the success on each task (columns) at each evaluation (rows: after "
                         "after_tasks tasks); null: not learnt by then",
            "after_tasks": after,
            "mean": _rows(np.stack([mean_se(np.where(later.valid[:, p], later.success_rate[:, p], np.nan))[0]
                                    for p in rows])),
        },
    }


def forward_transfer_summary(raw: results_.RawResults, reference_raw: Optional[results_.RawResults],
                             reference: Optional[str], ids: np.ndarray, horizon: int) -> dict:
    """Continual World's forward transfer of one entry against the ``reference`` entry (PPO from scratch;
    ``FT_REFERENCE``): per seed and task FT = (AUC − AUC_ref)/(1 − AUC_ref), AUC the success rate averaged over
    ``horizon`` iterations (``continual_metrics.auc``), AUC_ref the reference's averaged over its seeds on the same
    task (``ids`` [seeds, num_tasks]: each seed's task values). A ``note`` when the run has no reference."""
    if reference_raw is None:
        return {"reference": None, "note": f"not measured: no {FT_REFERENCE} (from scratch) in this run; merge a run "
                                           f"of {FT_REFERENCE} with the same options (experiments/merge_runs.py)"}
    own, ref = raw.per_task.task.per_iteration, reference_raw.per_task.task.per_iteration
    a, ref_a, ft = statistics.forward_transfer(own.success_rate, own.valid, ref.success_rate, ref.valid, ids, horizon)
    return {
        "reference": reference,
        "statistic": f"per seed and task: (AUC − AUC_ref)/(1 − AUC_ref), AUC the mean success rate over {horizon} "
                     "iterations (the last one carried past an early stop), AUC_ref the reference's mean over its "
                     "seeds on the same task; mean and s.e. over seeds of each seed's mean over the tasks",
        "horizon": int(horizon),
        "auc": _rows(a),
        "reference_auc": _rows(ref_a),
        "per_task": _rows(ft),
        "per_task_mean": _rows(mean_se(ft)[0]),
        **_over_seeds(statistics.nanmean(ft, axis=1)),
    }


def probability_of_improvement(raw: results_.RawResults, baseline_raw: results_.RawResults, baseline: str) -> dict:
    """rliable's probability that a run of this entry needs fewer iterations-to-success than a run of the
    ``baseline`` on the same task (position), averaged over tasks, with a 95% stratified-bootstrap interval."""
    return {"over": baseline,
            "statistic": f"P(iterations-to-success < {baseline}'s; ties count 1/2) per task over pairs of seeds "
                         "(Mann-Whitney), averaged over tasks; 95% stratified-bootstrap interval",
            **statistics.probability_of_fewer_iterations(raw.per_task.task.iterations,
                                                         baseline_raw.per_task.task.iterations)}


def critic_summary(per_iteration) -> dict:
    """The RL step's critic for ``results.json``: per seed and task, its explained variance of the value targets
    (mean over the iterations that updated, the first and the last of them) and its value loss (mean over the same
    iterations); null where not measured (runs made before jcomps measured it, PEARL's Q-critics)."""
    fit = statistics.critic_fit(per_iteration.value_ev, per_iteration.value_loss, per_iteration.valid)
    rows = lambda x: [[_json_float(round(float(v), 6)) for v in row] for row in x]  # noqa: E731
    return {"statistic": "per seed and task, over the RL step's iterations that updated: the critic's explained "
                         "variance of its value targets (the GAE lambda-returns) on the iteration's batch before "
                         "the update, and the value loss",
            "value_ev_mean": rows(fit.ev_mean), "value_ev_first": rows(fit.ev_first),
            "value_ev_last": rows(fit.ev_last), "value_loss_mean": rows(fit.value_loss)}


def policy_summary(health) -> dict:
    """The exploration and plasticity of the policy each task's RL step started from and ended with
    (``jcomps.training.plasticity.PolicyHealth`` with leading [seeds, tasks]) for ``results.json``: per seed and task,
    its std (mean over action dimensions), its entropy, and per hidden layer the fraction of saturated tanh units;
    the means over seeds per task beside them."""
    rows = lambda x: np.round(np.asarray(x, np.float64), 6).tolist()  # noqa: E731
    out = {"statistic": "per seed and task: the policy the task's RL step started from (start) and ended with (end): "
                        "exploration std (mean over action dimensions), Gaussian entropy (nats), and per hidden "
                        f"layer the fraction of tanh units with |h| >= {plasticity.SATURATION} on at least "
                        f"{plasticity.SATURATED_SHARE:.0%} of the states of the task's first (start) or last (end) "
                        "iteration"}
    for key, value in health._asdict().items():
        out[key] = rows(value)
        out[key + "_mean"] = rows(np.mean(np.asarray(value, np.float64), axis=0))
    return out


def meta_summary(meta) -> dict:
    """The health of a method's meta phases (``jcomps.training.meta.MetaMetrics`` with leading [seeds, tasks]) for
    ``results.json``: per seed and task, means over the seen slots at the start (before the first outer step,
    after the new head was initialised) and the end of the meta phase that followed the task, on each slot's whole
    stores; the newest task's head (slot = task position) and the oldest task's importance weights apart; and the
    per-slot explained variances, weights and inner-step gains (L_BC(θ) − L_BC(φ_j): what one inner step gains on
    the task's skilled data) at the end."""
    start = {k: np.asarray(v, np.float64) for k, v in meta.start._asdict().items()}
    end = {k: np.asarray(v, np.float64) for k, v in meta.end._asdict().items()}
    seeds, tasks, _ = end["value_ev"].shape
    newest = lambda x: x[:, np.arange(tasks), np.arange(tasks)]  # noqa: E731 - slot t after task t
    over_seen = lambda x: cm.nanmean(x, axis=-1)  # noqa: E731 - unseen slots (and gains not measured) are NaN
    rows = lambda x: [[_json_float(round(float(v), 6)) for v in row] for row in x]  # noqa: E731
    out = {
        "statistic": "per seed and task: mean over the seen tasks' slots, each on its whole stores, at the start "
                     "and the end of the meta phase after the task",
        "value_ev_start": rows(over_seen(start["value_ev"])),
        "value_ev_end": rows(over_seen(end["value_ev"])),
        "newest_value_ev_start": rows(newest(start["value_ev"])),
        "newest_value_ev_end": rows(newest(end["value_ev"])),
        "value_ev_targets_end": rows(over_seen(end["value_ev_targets"])),
        "value_bias_over_return_std_start": rows(over_seen(start["value_bias"] / start["return_std"])),
        "value_bias_over_return_std_end": rows(over_seen(end["value_bias"] / end["return_std"])),
        "value_l2_end": rows(over_seen(end["value_l2"])),
        "adv_abs_end": rows(over_seen(end["adv_abs"])),
        "rho_end": rows(over_seen(end["rho"])),
        "oldest_rho_end": rows(end["rho"][:, :, 0]),
        "bc_loss_start": rows(over_seen(start["bc_loss"])),
        "bc_loss_end": rows(over_seen(end["bc_loss"])),
        "inner_gain_start": rows(over_seen(start["inner_gain"])),
        "inner_gain_end": rows(over_seen(end["inner_gain"])),
        "newest_inner_gain_end": rows(newest(end["inner_gain"])),
        "per_slot_value_ev_end": [[rows(end["value_ev"][s, t:t + 1, :t + 1])[0] for t in range(tasks)]
                                  for s in range(seeds)],
        "per_slot_rho_end": [[rows(end["rho"][s, t:t + 1, :t + 1])[0] for t in range(tasks)] for s in range(seeds)],
        "per_slot_inner_gain_end": [[rows(end["inner_gain"][s, t:t + 1, :t + 1])[0] for t in range(tasks)]
                                    for s in range(seeds)],
    }
    for key in ("value_ev_end", "newest_value_ev_start", "rho_end", "inner_gain_end"):
        out[key + "_mean"] = [_json_float(round(float(v), 6)) for v in cm.nanmean(
            np.asarray([[np.nan if v is None else v for v in row] for row in out[key]], np.float64), axis=0)]
    return out


def significance_table(results: dict) -> str:
    """Markdown tables: the baseline against each other method (t-test and bootstrap), and every method's IQM of
    iterations-to-success with stratified-bootstrap confidence intervals over each half of the sequence."""
    sig = results.get("significance")
    fmt = lambda v: "n/a" if v is None else f"{v:.4g}"  # noqa: E731
    if not sig:
        lines = ["No significance table: the run has no `comps`; name the method to compare against with "
                 "`--baseline METHOD` (`experiments/report.py DIR --baseline METHOD` redoes it).", ""]
    else:
        b = sig["baseline"]
        lines = [f"Statistic: {sig['statistic']}; two-sided independent t-test, bootstrap of "
                 f"{BOOTSTRAP_SAMPLES:,} resamples.", "",
                 f"| {b} vs | {b} mean | other mean | t | p (t-test) | p (bootstrap) |", "|---|---|---|---|---|---|"]
        for name, s in sig["against"].items():
            lines.append(f"| {name} | {s['mean_a']:.2f} | {s['mean_b']:.2f} | {fmt(s['t'])} | {fmt(s['p_ttest'])} | "
                         f"{fmt(s['p_bootstrap'])} |")
        lines.append("")
    shown = results.get("best", {m: m for m in results["methods"]}).values()
    entries = {name: results["methods"][name] for name in shown}
    halves = [h["tasks"] for h in next(iter(entries.values()))["iqm"]]
    lines += ["Interquartile mean (IQM) of iterations-to-success over seeds × tasks, with 95% confidence intervals "
              f"from a stratified bootstrap over seeds ({IQM_BOOTSTRAP_SAMPLES:,} resamples; Agarwal et al. 2021).",
              "", "| method | " + " | ".join(f"tasks {a}-{b}" for a, b in halves) + " |",
              "|---" * (len(halves) + 1) + "|"]
    for name, m in entries.items():
        cells = [f"{h['iqm']:.1f} [{fmt(h['ci'][0])}, {fmt(h['ci'][1])}]" for h in m["iqm"]]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n\n" + field_table(results, entries)


def field_table(results: dict, entries: dict) -> str:
    """Markdown table of the continual-RL field's metrics of ``entries`` ({name: results entry}): average
    performance, forgetting, forward transfer (mean ± s.e. over seeds) and the probability of improvement over the
    baseline with its interval."""
    sig = results.get("significance")
    baseline = sig["baseline"] if sig else None
    some = next(iter(entries.values()))
    reference = some["forward_transfer"].get("reference")
    pm = lambda d: "n/a" if d.get("mean") is None else (  # noqa: E731
        f"{d['mean']:.3f} ± {'n/a' if d.get('se') is None else format(d['se'], '.3f')}")
    head = ["average performance", "forgetting", f"forward transfer vs {reference or FT_REFERENCE}"]
    if baseline:
        head.append(f"P(fewer iterations than {baseline})")
    after = some["forgetting"].get("after_tasks")
    lines = ["Continual-RL metrics (Continual World, Wolczyk et al. 2021; rliable, Agarwal et al. 2021), mean ± s.e. "
             "over seeds: success rates on the tasks learnt, evaluated with fresh episodes"
             + (f" after {after} tasks" if after else "") + " (average performance) and right after each was "
             "learnt (forgetting = then − now); forward transfer from the RL step's success curves against "
             f"{reference or FT_REFERENCE} from scratch"
             + ("" if reference else f" (n/a: no {FT_REFERENCE} in this run)")
             + ("; probability of improvement in iterations-to-success per task (Mann-Whitney over seeds, "
                "averaged over tasks) with a 95% stratified-bootstrap interval" if baseline else "") + ".", "",
             "| method | " + " | ".join(head) + " |", "|---" * (len(head) + 1) + "|"]
    for name, m in entries.items():
        cells = [pm(m["average_performance"]), pm(m["forgetting"]), pm(m["forward_transfer"])]
        if baseline:
            poi = sig.get("probability_of_improvement", {}).get(name)
            cells.append("–" if poi is None else f"{poi['probability']:.3f} [{poi['ci'][0]:.3f}, {poi['ci'][1]:.3f}]")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def grid_table(results: dict, grid: grids.Grid) -> str:
    """Markdown table of every grid point of ``grid`` (the run's): mean iterations-to-success ± s.e. and mean
    return, best marked."""
    if not grid:
        return ""
    fields = [axis.field for axis in grid]
    best = set(results.get("best", {}).values())
    seeds = len(results["seeds"])
    fmt = lambda v: "n/a" if v is None else f"{v:.2f}"  # noqa: E731
    lines = [f"Every grid point ({seeds} seeds each): iterations-to-success averaged over tasks and seeds ± the "
             "standard error of the per-seed means, mean return over tasks and seeds; **best** is each method's "
             "lowest mean iterations-to-success (ties: higher return), the point the plots and the table above "
             "use.", "",
             "| method | " + " | ".join(fields) + " | iterations-to-success | mean return | |",
             "|---" * (len(fields) + 4) + "|"]
    for name, m in results["methods"].items():
        o = m.get("overall", {})
        cells = [grids.format_value(m.get("grid", {})[f]) if f in m.get("grid", {}) else "–" for f in fields]
        lines.append(f"| {m.get('method', name)} | " + " | ".join(cells) +
                     f" | {fmt(o.get('iterations_to_success_mean'))} ± {fmt(o.get('iterations_to_success_se'))} | "
                     f"{fmt(o.get('mean_return'))} | {'**best**' if name in best else ''} |")
    return "\n".join(lines) + "\n"


def read_raws(out: str, description: RunDescription, partial: bool = False) -> tuple[dict, Optional[dict]]:
    """{entry key: RawResults} of run directory ``out``, and None. With ``partial``, an unfinished entry
    contributes the tasks it has finished (``raw/partial/``), every entry is cut to the tasks all of them have
    finished, and the second value says so: {"tasks": k, "of": N, "tasks_done": {entry: tasks}} (None when every
    entry has finished). RunError names an entry with nothing to report."""
    raws, done = {}, {}
    for _, name, _ in description.entries():
        raw = results_.load(out, name)
        if raw is None and partial:
            raw = results_.load_partial(out, name)
            if raw is None:
                raise RunError(f"{out}: {name} has not finished a chunk of tasks yet; nothing to report")
        if raw is None:
            raise RunError(f"{out}: {name} has not finished; continue the run with --resume, or report "
                           "the tasks every method has finished with --partial")
        raws[name], done[name] = raw, results_.tasks_done(raw)
    num_tasks = description.run.num_tasks
    common = min(done.values())
    if common == num_tasks:
        return raws, None
    return ({name: results_.truncate(raw, common) for name, raw in raws.items()},
            {"tasks": common, "of": num_tasks, "tasks_done": done})


def write(out: str, baseline: Optional[str] = None, partial: bool = False) -> Optional[dict]:
    """(Re)writes ``results.json``, the plots and ``significance.md`` of run directory ``out``; the significance
    table compares ``baseline`` (default: ``comps`` when the run has it) with every other method. With
    ``partial`` an unfinished run is reported on the tasks all its entries have finished (``read_raws``)."""
    description = rundir.read(out)
    raws, cut = read_raws(out, description, partial)
    results = summarize(description, raws, baseline)
    if cut is not None:
        results["partial"] = cut
    results["plots"] = [os.path.relpath(p, out)
                        for p in plots.write(results, raws, os.path.join(out, "plots"), description)]
    write_json(os.path.join(out, "results.json"), results)
    table = grid_table(results, description.grid)
    head = "" if cut is None else (
        f"Unfinished run: tasks 1-{cut['tasks']} of {cut['of']}, the tasks every method has finished (tasks done: "
        + ", ".join(f"{name} {k}" for name, k in cut["tasks_done"].items()) + ").\n\n")
    with open(os.path.join(out, "significance.md"), "w") as f:
        f.write(head + significance_table(results) + ("\n## Grid\n\n" + table if table else ""))
    return results
