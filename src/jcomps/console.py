"""What the runner shows and logs: progress lines, per-task results, TensorBoard and W&B, from the events of
``jcomps.runner.experiment`` (its one ``progress_fn`` callback; every kind of event: ``jcomps.runner.events``). The
edge of the package, above the report (tests/test_layout.py): the scripts in ``experiments/`` use it, and nothing
else under ``src/jcomps`` prints.
"""

from __future__ import annotations

import os
import time
from typing import Callable, Optional

import numpy as np

from jcomps.analysis import continual_metrics as cm
from jcomps.analysis import statistics
from jcomps.runner import events
from jcomps.runner.files import RunError


class Progress:
    """Host-side progress of one program: a status line at most every ``interval`` seconds, from the callbacks
    of every RL iteration (program, task, iteration, success rate, the critic's explained variance, elapsed,
    remaining) and of every outer update
    of a meta-training phase (program, task, meta step, outer BC loss, elapsed, remaining).

    ``members`` (a program of several grid points): each member's name (its grid point and seed); the line then
    also names the member furthest behind, so one line per program says which grid point it waits for.
    """

    def __init__(self, name: str, seeds: int, num_tasks: int, start_task: int, log: Callable[[str], None],
                 interval: float = 10.0, members: Optional[list] = None):
        self.name, self.seeds, self.num_tasks, self.log, self.interval = name, seeds, num_tasks, log, interval
        self.members = members
        self.start = time.time()
        self.start_task = start_task
        self.last = 0.0
        self.task = np.full(seeds, start_task, np.int64)
        self.iteration = np.zeros(seeds, np.int64)
        self.success = np.zeros(seeds)
        self.value_ev = np.full(seeds, np.nan)  # the RL step's critic: each member's latest measured fit
        self.meta_loss = np.full(seeds, np.nan)
        self.meta_health = np.full((seeds, 5), np.nan)  # value l2, value EV on returns, mean |Â|, mean ρ, inner gain
        self.heldout_begin()

    def restart_clock(self):
        """Elapsed and remaining count from now (after the learning program compiled)."""
        self.start = time.time()

    def resumed(self, tasks_done: int):
        """The run continues after ``tasks_done`` tasks."""
        self.start_task = tasks_done
        self.task[:] = tasks_done

    def heldout_begin(self):
        """A held-out meta-test begins: its progress lines count from now."""
        self.heldout_start = time.time()
        self.heldout_iteration = np.zeros((len(self.task), 0), np.int64)

    def record_heldout(self, member: int, heldout_task: int, iteration: int):
        """After every PPO iteration of a member's adaptation to a held-out task."""
        h = self.heldout_iteration
        if heldout_task >= h.shape[1]:
            h = np.concatenate([h, np.zeros((h.shape[0], heldout_task + 1 - h.shape[1]), np.int64)], axis=1)
        h[member, heldout_task] = iteration
        self.heldout_iteration = h
        self._throttled(lambda: f"[{self.name}] held-out meta-test: {h.shape[1]} held-out tasks, iteration "
                                f"{int(h.max())} (slowest {int(h.min())}) | elapsed "
                                f"{clock(time.time() - self.heldout_start)}")

    def record_iteration(self, member: int, task: int, iteration: int, success_rate: float,
                         value_ev: float = float("nan")):
        """After every RL iteration of a member (``value_ev``: the critic's fit its update measured, NaN if none;
        the line shows the members' latest measured)."""
        self.task[member], self.iteration[member], self.success[member] = task, iteration, success_rate
        if np.isfinite(value_ev):
            self.value_ev[member] = value_ev
        self._throttled(self.line)

    def record_meta_step(self, member: int, task: int, step: int, steps: int, loss: float,
                         health: Optional[tuple] = None):
        """After every outer update of a meta-training phase (between two tasks); ``health``: (value l2, value
        heads' explained variance on the returns, mean |Â|, mean clipped ρ, the inner step's gain in the outer loss),
        means over the seen tasks."""
        self.meta_loss[member] = float(loss)
        if health is not None:
            self.meta_health[member] = health
        self._throttled(lambda: f"[{self.name}] task {task + 1}/{self.num_tasks} meta-training step {int(step)}/"
                                f"{int(steps)} bc loss {float(np.nanmean(self.meta_loss)):.3f}{self._health()}"
                                f"{self._behind()} | elapsed {clock(time.time() - self.start)} remaining "
                                f"{self._remaining_text()}")

    def _health(self) -> str:
        if np.all(np.isnan(self.meta_health)):
            return ""
        l2, ev, adv, rho, gain = np.nanmean(self.meta_health, axis=0)
        return f" value l2 {l2:.3g} EV {ev:.2f} |A| {adv:.3g} rho {rho:.2f} inner gain {gain:+.3g}"

    def record_compress(self, member: int, task: int, step: int, steps: int, kl: float):
        """After every iteration of a compress phase (``pnc``: distilling the active column into the knowledge
        base, after the task's progress phase)."""
        self.meta_loss[member] = float(kl)
        self._throttled(lambda: f"[{self.name}] task {task + 1}/{self.num_tasks} compress iteration {int(step)}/"
                                f"{int(steps)} kl {float(np.nanmean(self.meta_loss)):.4f}{self._behind()} | "
                                f"elapsed {clock(time.time() - self.start)} remaining {self._remaining_text()}")

    # The member events (``jcomps.runner.events``), each to its record.
    def iteration(self, event: events.Iteration):
        self.record_iteration(event.member, event.task, event.iteration, event.success_rate, float(event.value_ev))

    def meta_step(self, event: events.MetaStep):
        health = (event.value_l2, event.value_ev, event.adv_abs, event.rho, event.inner_gain)
        self.record_meta_step(event.member, event.task, event.meta_step, event.meta_steps, event.bc_loss,
                              None if event.value_ev is None else tuple(np.nan if h is None else h for h in health))

    def compress_iteration(self, event: events.CompressIteration):
        self.record_compress(event.member, event.task, event.compress_iteration, event.compress_iterations, event.kl)

    def heldout_iteration(self, event: events.HeldoutIteration):
        self.record_heldout(event.member, event.heldout_task, event.heldout_iteration)

    def _throttled(self, line: Callable[[], str]):
        now = time.time()
        if now - self.last >= self.interval:
            self.last = now
            self.log(line())

    def _remaining_text(self) -> str:
        remaining = self.remaining()
        return "?" if remaining is None else "~" + clock(remaining)

    def _behind(self) -> str:
        if not self.members:
            return ""
        # The lowest task, then the highest iteration: a member that reached the threshold keeps reporting the
        # iteration it stopped at while the vmapped loop waits for the others, so the one still iterating on the
        # lowest task has counted furthest.
        m = int(np.lexsort((-self.iteration, self.task))[0])
        return f" | behind: {self.members[m]} (task {int(self.task[m]) + 1})"

    def remaining(self) -> Optional[float]:
        done = float(np.mean(self.task)) - self.start_task
        if done <= 0:
            return None
        return (time.time() - self.start) * (self.num_tasks - float(np.mean(self.task))) / done

    def line(self) -> str:
        lo, hi = int(self.task.min()) + 1, int(self.task.max()) + 1
        tasks = f"{lo}" if lo == hi else f"{lo}-{hi}"
        ev = "" if np.all(np.isnan(self.value_ev)) else f" critic EV {float(np.nanmean(self.value_ev)):.2f}"
        return (f"[{self.name}] task {tasks}/{self.num_tasks} iteration {int(self.iteration.max())} success "
                f"{float(self.success.mean()):.2f}{ev}{self._behind()} | elapsed {clock(time.time() - self.start)} "
                f"remaining {self._remaining_text()}")


def clock(seconds: float) -> str:
    seconds = int(seconds)
    return f"{seconds // 3600}h{seconds // 60 % 60:02d}m" if seconds >= 3600 else f"{seconds // 60}m{seconds % 60:02d}s"


class Console:
    """A ``jcomps.runner.experiment.ProgressReceiver``: prints progress lines (at most every ``interval`` seconds per
    program), every task's iterations-to-success, non-finite warnings and checkpoint warnings through ``log``; with
    ``tensorboard``, also writes TensorBoard logs under ``out/tensorboard/<entry>``, with ``wandb`` (a project) the
    same scalars to Weights & Biases (``WandbLogger``; ``close`` finishes its runs). Each kind of event
    (``jcomps.runner.events.EVENTS``) has its handler; kinds it does not show are ignored."""

    def __init__(self, log: Callable[[str], None] = print, out: Optional[str] = None, tensorboard: bool = False,
                 interval: float = 10.0, wandb: Optional[str] = None, wandb_group: Optional[str] = None):
        self.log, self.out, self.tensorboard, self.interval = log, out, tensorboard, interval
        self.progress: dict = {}
        self.writers: dict = {}
        if tensorboard:
            _tensorboard_writer_class()  # fail before anything runs if tensorboardX is missing
        self.wandb = WandbLogger(wandb, out, wandb_group) if wandb else None
        self.handlers = {
            events.Start: self._start, events.Compiling: self._compiling,
            events.StillCompiling: self._still_compiling, events.Compiled: self._compiled,
            events.Resumed: self._resumed, events.Evaluating: self._evaluating, events.Evaluated: self._evaluated,
            events.Warned: self._warning, events.Chunk: self._chunk, events.Done: self._done,
            events.Skipped: self._skipped,
        }
        # Progress inside a program's chunk, shown by its ``Progress`` once the program has started.
        self.member_handlers = {
            events.Iteration: Progress.iteration, events.MetaStep: Progress.meta_step,
            events.CompressIteration: Progress.compress_iteration, events.HeldoutIteration: Progress.heldout_iteration,
        }

    def __call__(self, event):
        kind = type(event)
        if kind in self.handlers:
            self.handlers[kind](event)
        elif kind in self.member_handlers and event.program in self.progress:
            self.member_handlers[kind](self.progress[event.program], event)

    def _start(self, event: events.Start):
        extra = f" (+{event.padding} to fill the devices, not reported)" if event.padding else ""
        points = event.grid_points
        grid_text = f" × {points} grid points = {points * event.seeds} members" if points > 1 else ""
        order = (f"tasks {' '.join(event.tasks)}" + (" (shuffled per seed)" if event.sequence == "stationary" else "")
                 if event.tasks else f"{event.sequence}, {event.num_tasks} tasks")
        self.log(f"[{event.program}] {event.family} {order}, {event.seeds} seeds{grid_text}{extra} on "
                 f"{event.devices} device(s), budget {event.budget}, chunks of {event.chunk}")
        self.progress[event.program] = Progress(event.program, len(event.members), event.num_tasks, event.start_task,
                                                self.log, self.interval, list(event.members) if points > 1 else None)

    def _compiling(self, event: events.Compiling):
        after = " (while the first task trains)" if event.part in ("evaluate_task", "measure") else ""
        self.log(f"[{event.program}] compiling the {event.what} program ({event.family}, {event.method}){after}...")

    def _still_compiling(self, event: events.StillCompiling):
        self.log(f"[{event.program}] still compiling the {event.what} program: {clock(event.seconds)}")

    def _compiled(self, event: events.Compiled):
        cached = "; from the compile cache" if event.cached else ""
        self.log(f"[{event.program}] {event.what} program ready in {clock(event.seconds)} (tracing "
                 f"{event.trace_seconds:.0f}s{cached})")
        if event.part == "learn" and event.program in self.progress:
            self.progress[event.program].restart_clock()

    def _resumed(self, event: events.Resumed):
        self.log(f"[{event.program}] resumed from checkpoint {event.step}: {event.tasks_done}/{event.num_tasks} "
                 "tasks done")
        if event.program in self.progress:
            self.progress[event.program].resumed(event.tasks_done)

    def _evaluating(self, event: events.Evaluating):
        what = "the initial policies" if event.after_tasks == 0 else f"the policies after task {event.after_tasks}"
        test = "held-out meta-test" if event.adapts else "held-out zero-shot return"
        self.log(f"[{event.program}] {test}{' and learnt tasks' if event.learnt else ''} of {what}...")
        if event.program in self.progress:
            self.progress[event.program].heldout_begin()

    def _evaluated(self, event: events.Evaluated):
        self.log(f"[{event.program}] evaluations after {event.after_tasks} task(s) done in {clock(event.seconds)}")

    def _warning(self, event: events.Warned):
        self.log(f"warning: {event.message}")

    def _chunk(self, event: events.Chunk):
        entry, start, stop, learnt = event.entry, event.start, event.stop, event.learnt_tasks
        _report_chunk(self.log, entry, event.metrics, start, stop, event.num_tasks)
        if learnt is not None and np.any(learnt.valid):
            self.log(f"[{entry}] after task {stop}/{event.num_tasks}: {learnt_text(event.per_task, learnt)}")
        _check_finite(self.log, entry, event.seeds, event.metrics.task.per_iteration.nonfinite, start)
        if self.tensorboard or self.wandb:
            scalars = chunk_scalars(event.per_task, start, stop, learnt)
            if self.tensorboard:
                if entry not in self.writers:
                    self.writers[entry] = _tensorboard_writer_class()(os.path.join(self.out, "tensorboard", entry))
                for tag, value, _, step in scalars:
                    self.writers[entry].add_scalar(tag, value, step)
                self.writers[entry].flush()
            if self.wandb:
                self.wandb.log(entry, scalars)

    def close(self):
        """Closes the TensorBoard writers and finishes the W&B runs."""
        for writer in self.writers.values():
            writer.close()
        self.writers = {}
        if self.wandb:
            self.wandb.close()

    def _done(self, event: events.Done):
        self.progress.pop(event.program, None)
        self.log(f"[{event.program}] done in {clock(event.seconds)}")

    def _skipped(self, event: events.Skipped):
        self.log(f"[{event.program}] already finished; skipping")


def _tensorboard_writer_class():
    try:
        from tensorboardX import SummaryWriter
    except ImportError as err:
        raise RunError("--tensorboard needs tensorboardX: pip install -e '.[tensorboard]'") from err
    return SummaryWriter


def _report_chunk(log, name, metrics, start, stop, num_tasks):
    its = np.asarray(metrics.task.iterations)[:, :stop - start]
    meta = metrics.task.meta
    per_it = metrics.task.per_iteration
    fit = statistics.critic_fit(*(np.asarray(x)[:, :stop - start] for x in (per_it.value_ev, per_it.value_loss,
                                                                           per_it.valid)))
    for t in range(stop - start):
        log(f"[{name}] task {start + t + 1}/{num_tasks} iterations-to-success per seed: {its[:, t].tolist()} "
            f"(mean {its[:, t].mean():.1f}){critic_text(fit, t)}")
        health = metrics.task.policy_health
        if health is not None:
            log(f"[{name}] task {start + t + 1}/{num_tasks} policy: {policy_health_text(health, t)}")
        if meta is not None:
            log(f"[{name}] task {start + t + 1}/{num_tasks} meta phase: {meta_health_text(meta, t, start + t)}")


def policy_health_text(health, t: int) -> str:
    """The policy that task position ``t`` of ``health`` (``jcomps.training.plasticity.PolicyHealth`` with leading
    [seeds, tasks]) started from and ended with, means over seeds: its exploration std, entropy and the fraction of
    saturated units per hidden layer."""
    at = lambda x: np.asarray(x)[:, t]  # noqa: E731
    layers = lambda x: "/".join(f"{v:.2f}" for v in at(x).mean(axis=0))  # noqa: E731
    return (f"std {at(health.std_start).mean():.3g} -> {at(health.std_end).mean():.3g} (per seed at the start "
            f"{', '.join(f'{v:.3g}' for v in at(health.std_start))}), entropy {at(health.entropy_start).mean():.3g} -> "
            f"{at(health.entropy_end).mean():.3g}, saturated units per layer {layers(health.saturated_start)} -> "
            f"{layers(health.saturated_end)}")


def critic_text(fit, t: int) -> str:
    """The RL step's critic on task position ``t`` of ``fit`` (``statistics.CriticFit`` [seeds, tasks]), means over
    seeds: its explained variance of the value targets over the task's updates and at the last, and its value
    loss; nothing where it was not measured."""
    ev, last, loss = (cm.nanmean(np.asarray(x)[:, t]) for x in (fit.ev_mean, fit.ev_last, fit.value_loss))
    if not np.isfinite(ev):
        return ""
    return f"; critic EV {ev:.2f} (last update {last:.2f}), value loss {loss:.3g}"


def learnt_text(per_task, learnt) -> str:
    """One line on the evaluation of the tasks learnt so far (``learnt``: a ``continual.Evaluation`` [seeds,
    num_tasks]), against the same tasks' evaluations right after each was learnt (``per_task.learnt``): mean
    success over seeds and tasks then and now, and their difference (forgetting)."""
    now, then = _learnt_means(per_task, learnt)
    n = int(np.asarray(learnt.valid).sum(1).max())
    return (f"success on the {n} task{'s' if n > 1 else ''} learnt {now:.2f}, right after learning "
            f"{'each' if n > 1 else 'it'} {then:.2f} (forgetting {then - now:+.2f})")


def _learnt_means(per_task, learnt) -> tuple[float, float]:
    """Mean success over seeds and the tasks evaluated in ``learnt``: now, and right after each was learnt."""
    valid = np.asarray(learnt.valid)
    return (float(np.asarray(learnt.success_rate)[valid].mean()),
            float(np.asarray(per_task.learnt.success_rate)[valid].mean()))


def meta_health_text(meta, t: int, slot: int) -> str:
    """One line on the meta phase after task position ``t`` of ``meta`` (``jcomps.training.meta.MetaMetrics`` with
    leading [seeds, tasks]; ``slot``: that task's experience slot): the value heads' fit to their data's returns before
    and after, the newest head's, how much the old tasks still contribute, and what the inner step gains in the outer
    loss (L(θ) − L(φ_j), mean over the seen slots, and the newest task's)."""
    start = _at_task(meta.start, t)
    end = _at_task(meta.end, t)
    mean = lambda x: float(np.nanmean(x))  # noqa: E731 - over seeds and seen slots
    return (f"heads' EV on returns {mean(start.value_ev):.2f} -> {mean(end.value_ev):.2f} (newest head "
            f"{mean(start.value_ev[:, slot]):.2f} -> {mean(end.value_ev[:, slot]):.2f}), bias/std "
            f"{mean(end.value_bias / end.return_std):+.2f}, mean rho {mean(end.rho):.2f} (oldest task "
            f"{mean(end.rho[:, 0]):.2f}), |A| {mean(end.adv_abs):.3g}, bc loss {mean(end.bc_loss):.3f}, inner gain "
            f"{mean(end.inner_gain):+.3g} (newest task {mean(end.inner_gain[:, slot]):+.3g})")


def _at_task(stats, t: int):
    """The fields of a SlotStats [seeds, tasks, slots] at task position ``t``, as numpy [seeds, slots]."""
    return type(stats)(*[np.asarray(x)[:, t] for x in stats])


def _check_finite(log, name, seeds, nonfinite, start):
    bad = np.argwhere(np.asarray(nonfinite) > 0)
    if len(bad):
        s, t, it = bad[0]
        log(f"error: [{name}] non-finite values (NaN/inf) at seed {seeds[s]}, task {start + t + 1}, iteration "
            f"{it + 1}; those updates were skipped, not trained on")


def chunk_scalars(per_task, start: int, stop: int, learnt=None) -> list[tuple[str, float, str, int]]:
    """The scalars of tasks ``start`` … ``stop`` − 1 that TensorBoard and W&B get: (tag, value, axis, step), the
    axis ``task`` (iterations-to-success, the policy's std, entropy and saturation at the task's start and end, the
    learnt tasks' metrics after the chunk) or ``iteration/seed<s>`` (the
    seed's iterations over the whole sequence: lifelong return and success, the critic's explained variance and
    value loss where the iteration updated)."""
    task = per_task.task
    its = np.asarray(task.iterations)
    out = []
    health = task.policy_health
    for t in range(start, stop):
        out.append(("iterations_to_success/mean", float(its[:, t].mean()), "task", t + 1))
        if health is not None:  # the policy each task started from and ended with, means over seeds
            for key in ("std_start", "std_end", "entropy_start", "entropy_end"):
                out.append((f"policy/{key}", float(np.mean(np.asarray(getattr(health, key))[:, t])), "task", t + 1))
            for layer, value in enumerate(np.asarray(health.saturated_end)[:, t].mean(axis=0)):
                out.append((f"policy/saturated_end/layer{layer + 1}", float(value), "task", t + 1))
        for s in range(its.shape[0]):
            out.append((f"iterations_to_success/seed{s}", float(its[s, t]), "task", t + 1))
        for s in range(its.shape[0]):
            valid = np.asarray(task.per_iteration.valid[s, t])
            offset = int(np.sum(np.asarray(task.per_iteration.valid[s, :t])))
            axis = f"iteration/seed{s}"
            for i in np.flatnonzero(valid):
                step = offset + int(i) + 1
                out.append((f"lifelong_return/seed{s}", float(task.per_iteration.mean_return[s, t, i]), axis, step))
                out.append((f"lifelong_success/seed{s}", float(task.per_iteration.success_rate[s, t, i]), axis, step))
                ev = float(task.per_iteration.value_ev[s, t, i])
                if np.isfinite(ev):  # measured where the iteration updated
                    out.append((f"critic_ev/seed{s}", ev, axis, step))
                    out.append((f"critic_value_loss/seed{s}", float(task.per_iteration.value_loss[s, t, i]), axis,
                                step))
    if learnt is not None and np.any(learnt.valid):
        now, then = _learnt_means(per_task, learnt)
        out.append(("learnt_tasks/average_performance", now, "task", stop))
        out.append(("learnt_tasks/forgetting", then - now, "task", stop))
    return out


class WandbLogger:
    """Weights & Biases runs, one per results entry, with the scalars TensorBoard gets (``chunk_scalars``): each on
    its own axis (``task``, or a seed's ``iteration/seed<s>``) declared with ``define_metric``, so that W&B draws
    them as TensorBoard does. Offline unless ``WANDB_MODE`` says otherwise (``wandb sync OUT/wandb/offline-run-*``
    uploads later); the files go to ``OUT/wandb``; no API key or network is needed offline."""

    def __init__(self, project: str, out: str, group: Optional[str] = None):
        try:
            import wandb
        except ImportError as err:
            raise RunError("--wandb needs wandb: pip install -e '.[wandb]'") from err
        self.wandb, self.project, self.out, self.group = wandb, project, out, group
        self.mode = os.environ.get("WANDB_MODE", "offline")
        # Process-wide: offline and silent before any run (a mode given to init alone still probes the server).
        wandb.setup(settings=wandb.Settings(mode=self.mode, silent=True))
        self.runs: dict = {}
        self.axes: dict = {}

    def _run(self, entry: str):
        if entry not in self.runs:
            os.makedirs(self.out, exist_ok=True)
            run = self.wandb.init(
                project=self.project, dir=self.out, name=entry, group=self.group or os.path.basename(self.out),
                job_type="sequence", mode=self.mode, reinit="create_new",
                settings=self.wandb.Settings(console="off", x_disable_stats=True, disable_git=True,
                                             x_save_requirements=False))
            run.define_metric("task")
            run.define_metric("iterations_to_success/*", step_metric="task")
            run.define_metric("learnt_tasks/*", step_metric="task")
            self.runs[entry], self.axes[entry] = run, set()
        return self.runs[entry]

    def log(self, entry: str, scalars) -> None:
        """Logs ``scalars`` ((tag, value, axis, step), as ``chunk_scalars`` gives them): one row per axis and step."""
        run, axes = self._run(entry), self.axes[entry]
        rows: dict = {}
        for tag, value, axis, step in scalars:
            if axis != "task" and tag not in axes:
                run.define_metric(axis, hidden=True)
                run.define_metric(tag, step_metric=axis)
                axes.add(tag)
            rows.setdefault((axis, step), {axis: step})[tag] = value
        for row in rows.values():
            run.log(row)

    def close(self) -> None:
        """Finishes the runs and stops wandb's service, which writes out what it still holds."""
        for run in self.runs.values():
            run.finish()
        self.runs = {}
        self.wandb.teardown()
