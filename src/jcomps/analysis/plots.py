"""The paper's plots of a run, drawn from its ``results.json`` content (and the raw lifelong return curves) into
``plots/*.png``: iterations and samples to success, lifelong and per-task return, backward transfer, the held-out
meta-test, the meta step's health, performance profiles and the continual-RL field's metrics.

Figures are matplotlib ``Figure`` objects saved straight to PNG (no pyplot, so no GUI backend and no global figure
state).
"""

from __future__ import annotations

import os
from typing import Callable, Optional

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from jcomps.analysis.statistics import FT_REFERENCE, mean_se


def _floats(rows) -> np.ndarray:
    """f64[a, b] of nested lists from ``results.json``, null (None) as NaN."""
    return np.array([[np.nan if v is None else v for v in row] for row in rows], np.float64)


def _figure(figsize, cols: int = 1, **kwargs):
    """A figure of ``figsize`` inches and its ``cols`` axes side by side (one axes when ``cols`` is 1)."""
    fig = Figure(figsize=figsize)
    return fig, fig.subplots(1, cols, **kwargs)


def _integer_ticks(ax) -> None:
    """Whole-number ticks on the x axis: task numbers and tasks learnt."""
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))


def _band(ax, x, values, label: str) -> None:
    """The mean over seeds of ``values`` f[S, len(x)] as a line with a ±1 standard-error band."""
    mean, se = mean_se(values)
    ax.plot(x, mean, marker="o", ms=3, label=label)
    ax.fill_between(x, mean - se, mean + se, alpha=0.25)


def _errorbar(ax, x, mean, se, color: str, label: str) -> None:
    """``mean`` at ``x`` with ±``se`` error bars."""
    ax.errorbar(x, mean, yerr=se, marker="o", ms=3, color=color, label=label)


def _legend_or(ax, missing: Optional[str] = None, **kwargs) -> None:
    """The legend of ``ax`` when it has labelled artists; otherwise ``missing`` (if any) in gray at its centre."""
    if ax.get_legend_handles_labels()[0]:
        ax.legend(**kwargs)
    elif missing is not None:
        ax.text(0.5, 0.5, missing, transform=ax.transAxes, ha="center", color="gray")


def _task_bands(save: Callable, name: str, tasks, series: dict, ylabel: str, title: str,
                hline: Optional[float] = None, missing: Optional[str] = None) -> None:
    """One figure ``name`` of a band per entry of ``series`` ({label: f[S, len(tasks)]}) over the tasks."""
    fig, ax = _figure((6, 4))
    for label, values in series.items():
        _band(ax, tasks, values, label)
    if hline is not None:
        ax.axhline(hline, color="gray", lw=0.8, ls="--")
    ax.set(xlabel="task", ylabel=ylabel, title=title)
    _integer_ticks(ax)
    _legend_or(ax, missing)
    save(fig, name)


def _lifelong_return(save: Callable, raws: dict) -> None:
    """Every iteration's mean return over the sequence: thin per seed, thick the mean while all seeds run."""
    fig, ax = _figure((7, 4))
    for k, (name, raw) in enumerate(raws.items()):
        valid, ret = raw.per_task.task.per_iteration.valid, raw.per_task.task.per_iteration.mean_return
        lines = [ret[s][valid[s]] for s in range(ret.shape[0])]
        n = min(len(x) for x in lines)
        for line in lines:
            ax.plot(np.arange(1, len(line) + 1), line, color=f"C{k}", alpha=0.2, lw=0.7)
        ax.plot(np.arange(1, n + 1), np.mean([x[:n] for x in lines], axis=0), color=f"C{k}", label=name)
    ax.set(xlabel="iteration of the sequence", ylabel="mean return",
           title="Lifelong return (thin: seeds; thick: mean while all seeds run)")
    ax.legend()
    save(fig, "lifelong_return.png")


def _heldout(save: Callable, methods_: dict) -> None:
    """The held-out meta-test after each chunk: iterations to success and the return before and after adapting.
    Not drawn when no method adapted on the held-out tasks (the test off: ``--heldout-iterations 0
    --heldout-budget 0``, the default; results.json still has their zero-shot return)."""
    if all(m["heldout"]["adaptation_iterations"] == 0 and m["heldout"]["budget"] == 0 for m in methods_.values()):
        return
    fig, (ax_its, ax) = _figure((11, 4), 2)
    for k_, (name, m) in enumerate(methods_.items()):
        h = m["heldout"]
        if h["budget"] > 0:
            _errorbar(ax_its, h["after_tasks"], *mean_se(np.asarray(h["iterations_to_success_mean"])), f"C{k_}", name)
        _errorbar(ax, h["after_tasks"], *mean_se(np.asarray(h["adapted_return"])), f"C{k_}",
                  f"{name} after {h['adaptation_iterations']} iterations")
        ax.plot(h["after_tasks"], np.mean(h["zero_shot_return"], axis=0), ls=":", color=f"C{k_}",
                label=f"{name} zero-shot")
    budget = max(m["heldout"]["budget"] for m in methods_.values())
    ax_its.set(xlabel="tasks learnt", ylabel=f"iterations to success (cap {budget})",
               title="Held-out tasks: iterations to success")
    ax.set(xlabel="tasks learnt", ylabel="mean return on held-out tasks", title="Held-out tasks: return")
    if budget == 0:
        ax_its.text(0.5, 0.5, "not measured (--heldout-budget 0)", ha="center", va="center", transform=ax_its.transAxes)
    for a in (ax_its, ax):
        _integer_ticks(a)
        _legend_or(a, fontsize=8)
    save(fig, "heldout_meta_test.png")


def _meta_health(save: Callable, with_meta: dict, tasks) -> None:
    """The meta step's health ({name: its ``meta`` summary}): the value heads' fit, the importance weights and the
    inner step's gain in the outer loss (runs made before it was measured have no gain to draw)."""
    fig, (ax_ev, ax_rho, ax_gain) = _figure((16.5, 4), 3)
    for k_, (name, m) in enumerate(with_meta.items()):
        ev, newest = _floats(m["value_ev_end"]), _floats(m["newest_value_ev_start"])
        ax_ev.plot(tasks, np.nanmean(ev, axis=0), marker="o", ms=3, color=f"C{k_}", label=f"{name}, all heads")
        ax_ev.plot(tasks, np.nanmean(newest, axis=0), ls=":", marker="x", ms=3, color=f"C{k_}",
                   label=f"{name}, newest head before its first step")
        ax_rho.plot(tasks, np.nanmean(_floats(m["rho_end"]), axis=0), marker="o", ms=3, color=f"C{k_}",
                    label=f"{name}, all tasks")
        ax_rho.plot(tasks, np.nanmean(_floats(m["oldest_rho_end"]), axis=0), ls=":", color=f"C{k_}",
                    label=f"{name}, task 1")
        if np.isfinite(_floats(m.get("inner_gain_end", [[np.nan]]))).any():  # not in runs made before it was measured
            ax_gain.plot(tasks, np.nanmean(_floats(m["inner_gain_end"]), axis=0), marker="o", ms=3, color=f"C{k_}",
                         label=f"{name}, mean over seen tasks")
            ax_gain.plot(tasks, np.nanmean(_floats(m["newest_inner_gain_end"]), axis=0), ls=":", marker="x", ms=3,
                         color=f"C{k_}", label=f"{name}, newest task")
    ax_ev.axhline(0.0, color="gray", lw=0.8, ls="--")
    ax_ev.set(xlabel="task", ylabel="explained variance of the returns",
              title="Meta step: value heads' fit to their data's returns")
    ax_rho.set(xlabel="task", ylabel="mean clipped importance weight",
               title="Meta step: how much the old tasks contribute")
    ax_gain.axhline(0.0, color="gray", lw=0.8, ls="--")
    ax_gain.set(xlabel="task", ylabel="L(θ) − L(φ_j) at the end of the meta phase",
                title="Meta step: what one inner step gains")
    for a in (ax_ev, ax_rho, ax_gain):
        _integer_ticks(a)
        _legend_or(a, fontsize=7)
    save(fig, "meta_health.png")


def _policy_health(save: Callable, with_policy: dict, tasks) -> None:
    """The policy each task starts from and ends with ({name: its ``policy`` summary}): its exploration std (log
    scale: a collapse shows), and the fraction of saturated hidden units per layer."""
    fig, (ax_std, ax_sat) = _figure((11, 4), 2)
    for k_, (name, p) in enumerate(with_policy.items()):
        ax_std.plot(tasks, np.mean(_floats(p["std_start"]), axis=0), marker="o", ms=3, color=f"C{k_}",
                    label=f"{name}, task start")
        ax_std.plot(tasks, np.mean(_floats(p["std_end"]), axis=0), ls=":", marker="x", ms=3, color=f"C{k_}",
                    label=f"{name}, task end")
        saturated = _floats(p["saturated_end"])  # [seeds, tasks, layers]
        for layer in range(saturated.shape[-1]):
            ax_sat.plot(tasks, np.mean(saturated[..., layer], axis=0), ls=("-", "--", ":", "-.")[layer % 4],
                        marker="o", ms=3, color=f"C{k_}", label=f"{name}, layer {layer + 1}")
    ax_std.set(xlabel="task", ylabel="exploration std (mean over action dimensions)", yscale="log",
               title="Policy: exploration std at each task's start and end")
    ax_sat.set(xlabel="task", ylabel="fraction of saturated tanh units", ylim=(-0.02, 1.02),
               title="Policy: saturated hidden units at each task's end")
    for a in (ax_std, ax_sat):
        _integer_ticks(a)
        _legend_or(a, fontsize=7)
    save(fig, "policy_health.png")


def _critic(save: Callable, methods_: dict, tasks) -> None:
    """The RL step's critic per task ({name: its ``critic`` summary}): its explained variance of the value targets
    (mean over the task's updating iterations, and at the last of them) and its value loss."""
    fig, (ax_ev, ax_loss) = _figure((11, 4), 2)
    for k_, (name, c) in enumerate(methods_.items()):
        ev, last = _floats(c["value_ev_mean"]), _floats(c["value_ev_last"])
        mean, se = mean_se(ev)
        ax_ev.plot(tasks, mean, marker="o", ms=3, color=f"C{k_}", label=f"{name}, mean over the RL step")
        ax_ev.fill_between(tasks, mean - se, mean + se, color=f"C{k_}", alpha=0.2)
        ax_ev.plot(tasks, mean_se(last)[0], ls=":", marker="x", ms=3, color=f"C{k_}", label=f"{name}, last update")
        _band(ax_loss, tasks, _floats(c["value_loss_mean"]), name)
    ax_ev.axhline(0.0, color="gray", lw=0.8, ls="--")
    ax_ev.set(xlabel="task", ylabel="explained variance of the value targets",
              title="RL step: the critic's fit (before each update)")
    ax_loss.set(xlabel="task", ylabel="value loss", yscale="log", title="RL step: the critic's value loss")
    for a in (ax_ev, ax_loss):
        _integer_ticks(a)
        _legend_or(a, fontsize=7)
    save(fig, "critic.png")


def _performance_profile(save: Callable, methods_: dict, title: str) -> None:
    """Each method's fraction of runs solved within τ iterations, with its bootstrap band."""
    fig, ax = _figure((6, 4))
    for k_, (name, m) in enumerate(methods_.items()):
        profile = m["performance_profile"]
        ax.step(profile["tau"], profile["fraction"], where="post", color=f"C{k_}", label=name)
        ax.fill_between(profile["tau"], profile["ci_low"], profile["ci_high"], step="post", color=f"C{k_}", alpha=0.2)
    ax.set(xlabel="tau (iterations)", ylabel="fraction of runs solved within tau", ylim=(-0.02, 1.02),
           title=f"Performance profile ({title})")
    ax.legend()
    save(fig, "performance_profile.png")


def _continual_metrics(save: Callable, methods_: dict, tasks) -> None:
    """Forgetting and forward transfer per task, and average performance after each evaluation."""
    fig, (ax_f, ax_ft, ax_p) = _figure((17, 4), 3, gridspec_kw={"wspace": 0.3})
    for k_, (name, m) in enumerate(methods_.items()):
        if "per_task" in m["forgetting"]:
            _band(ax_f, tasks, _floats(m["forgetting"]["per_task"]), name)
        if "per_task" in m["forward_transfer"]:
            _band(ax_ft, tasks, _floats(m["forward_transfer"]["per_task"]), name)
        by = m["average_performance"].get("by_evaluation")
        if by:
            _errorbar(ax_p, by["after_tasks"], [np.nan if v is None else v for v in by["mean"]],
                      [np.nan if v is None else v for v in by["se"]], f"C{k_}", name)
    some = next(iter(methods_.values()))
    after = some["forgetting"].get("after_tasks")
    reference = some["forward_transfer"].get("reference")
    ax_f.set(xlabel="task", ylabel="success when learnt − success later",
             title="Forgetting" + (f" after {after} tasks" if after else ""))
    ax_ft.set(xlabel="task", ylabel="(AUC − AUC_ref)/(1 − AUC_ref)",
              title=f"Forward transfer against {reference}" if reference else "Forward transfer")
    ax_p.set(xlabel="tasks learnt", ylabel="mean success on the tasks learnt", title="Average performance")
    for a, missing in ((ax_f, "not measured"), (ax_ft, f"no {FT_REFERENCE} in this run"), (ax_p, "not measured")):
        a.axhline(0.0, color="gray", lw=0.8, ls="--")
        _integer_ticks(a)
        _legend_or(a, missing, fontsize=8)
    save(fig, "continual_metrics.png")


def write(results: dict, raws: dict, directory: str, description) -> list[str]:
    """Draws every plot of ``results`` (the content of ``results.json``; ``raws``: {entry key: RawResults}, for
    the lifelong return; ``description``: the run's ``RunDescription``) into ``directory``, each method at its best
    grid point in a grid; returns the paths written, in order."""
    os.makedirs(directory, exist_ok=True)
    written = []
    run = description.run
    title = f"{run.family}, {run.sequence}, {run.seeds} seeds"
    if "best" in results:  # a grid: each method's best point
        title += ", best grid points"
        results = {**results, "methods": {k: results["methods"][k] for k in results["best"].values()}}
        raws = {k: raws[k] for k in results["best"].values()}

    def save(fig, name):
        path = os.path.join(directory, name)
        fig.savefig(path + ".tmp.png", dpi=110, bbox_inches="tight")
        os.replace(path + ".tmp.png", path)
        written.append(path)

    methods_ = results["methods"]
    tasks = np.arange(1, len(next(iter(methods_.values()))["iterations_to_success"][0]) + 1)
    _task_bands(save, "iterations_to_success.png", tasks,
                {name: np.asarray(m["iterations_to_success"]) for name, m in methods_.items()},
                "iterations to success", f"Iterations to success ({title})")
    _task_bands(save, "samples_to_success.png", tasks,
                {name: np.asarray(m["env_steps_to_success"]) for name, m in methods_.items()},
                "env steps to success", f"Samples to success ({title})")
    _lifelong_return(save, raws)
    _task_bands(save, "per_task_return.png", tasks,
                {name: np.asarray(m["mean_return_per_task"]) for name, m in methods_.items()},
                "average return during the RL step", "Per-task average return")
    backward = {name: _floats(m["backward_transfer"]) for name, m in methods_.items()}
    # One task (or a report cut to one): nothing learnt before it to forget.
    _task_bands(save, "backward_transfer.png", tasks, {k: v for k, v in backward.items() if np.any(np.isfinite(v))},
                "normalized reward (1: nothing forgotten)",
                f"Backward transfer on the previous {description.eval.backward_tasks} tasks",
                hline=1.0, missing="no earlier tasks to measure")
    _heldout(save, methods_)
    with_critic = {name: m["critic"] for name, m in methods_.items()
                   if np.isfinite(_floats(m.get("critic", {}).get("value_ev_mean", [[np.nan]]))).any()}
    if with_critic:  # not in older runs, nor for PEARL
        _critic(save, with_critic, tasks)
    with_policy = {name: m["policy"] for name, m in methods_.items() if "policy" in m}
    if with_policy:  # not in older runs, nor for PEARL
        _policy_health(save, with_policy, tasks)
    with_meta = {name: m["meta"] for name, m in methods_.items() if "meta" in m}
    if with_meta:
        _meta_health(save, with_meta, tasks)
    _performance_profile(save, methods_, title)
    _continual_metrics(save, methods_, tasks)
    return written
