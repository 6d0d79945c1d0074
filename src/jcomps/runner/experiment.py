"""Experiment runs: methods over a task sequence, seeds sharded over devices, chunked, checkpointed, resumable.

A run directory holds:

- ``run.json``: everything that defines the run (``jcomps.runner.rundir``); a resume must match it.
- ``checkpoints/<program>/<step>/``: checkpoints (``jcomps.runner.checkpoint``) of a program's entire state
  (parameters, optimiser states, experience stores, rng, counters) and the metrics so far, written after every
  chunk of tasks. A program is a method (``checkpoints/<method>``), or with a grid one per combination of its
  shape-changing values (``checkpoints/<method>@hidden_sizes=64x32``).
- ``raw/<entry>.npz``: all metrics of a results entry (a method, or a method at a grid point) once its program
  is done: a ``jcomps.runner.results.RawResults``, the input of ``jcomps.analysis.report``. Until then
  ``raw/partial/<entry>.npz`` holds the tasks finished so far, rewritten after every chunk
  (``report.py --partial`` reports a stopped run from them).
- ``results.json``, ``plots/*.png``, ``significance.md``: written by ``jcomps.analysis.report`` at the end.

Here is the host loop. A program's members (``jcomps.runner.members``: the seeds, or a grid's points × the seeds) run
through its compiled programs (``jcomps.runner.programs``): the host loops over the tasks of a chunk (``learn``, then
``evaluate_task``), measures after the chunk (``measure``) and checkpoints; since every chunk runs through the
same programs from the restored state, a resumed run gives per-task results identical to an uninterrupted one.

Nothing here prints: the outside world gets typed events (``jcomps.runner.events``) through one ``progress_fn``
callback (``ProgressReceiver``; ``jcomps.console`` turns them into progress lines and TensorBoard logs). Compiled programs live in a
``Programs`` cache owned by the caller, never in a module-level registry, so two runs never share progress.
``RunError`` (``jcomps.runner.files``) is what ``run`` raises for a run directory it cannot make or resume.
"""

from __future__ import annotations

import math
import os
import time
from typing import Callable, Optional

import jax
import numpy as np

from jcomps import continual, envs, methods
from jcomps.runner import distributed, events, results
from jcomps.runner import grid as grids
from jcomps.runner.checkpoint import Checkpoints, record, unflatten
from jcomps.runner.description import RunDescription
from jcomps.runner.files import RunError  # noqa: F401 - what run raises
from jcomps.runner.members import heldout_keys, layout, method_keys, num_devices, task_eval_keys, task_sequences
from jcomps.runner.programs import PART_NAMES, Programs
from jcomps.runner.rundir import open_run_dir

ProgressReceiver = Callable[[object], None]
"""The runner's one callback to the outside world (brax's ``progress_fn``), called on the host with one of
``jcomps.runner.events.EVENTS`` (typed events: each class says what it carries)."""


def _silent(event) -> None:
    del event


def run(out: str, description: RunDescription, resume: bool = False, progress_fn: ProgressReceiver = _silent,
        programs: Optional[Programs] = None) -> dict:
    """Runs every method of ``description`` into ``out`` (resuming where it stopped), each at every point of its
    hyperparameter grid (``jcomps.runner.grid``); returns RawResults by results entry key. Events go to
    ``progress_fn`` (``ProgressReceiver``); compiled programs are kept in ``programs`` (default: a fresh cache)."""
    open_run_dir(out, description, resume)
    programs = Programs() if programs is None else programs
    raws = {}
    for name in description.run.methods:
        for spec in description.programs(name):
            done = {p.key: results.load(out, p.key) for p in spec.points} if resume else {}
            finished = bool(done) and all(raw is not None for raw in done.values())
            if distributed.all_agree(finished, "deciding what is left to run"):  # every process skips it, or none
                progress_fn(events.Skipped(spec.label))
            else:
                done = run_program(out, spec, description, resume, progress_fn, programs)
            raws.update(done)
    return raws


def run_method(out: str, name: str, description: RunDescription, resume: bool,
               progress_fn: ProgressReceiver = _silent, programs: Optional[Programs] = None,
               stop_after_chunks: Optional[int] = None) -> Optional[results.RawResults]:
    """Runs (or resumes) method ``name`` of ``description`` (a run without a grid) in a run directory already
    opened (``jcomps.runner.rundir.open_run_dir``); returns its raw results when the sequence is done.

    ``stop_after_chunks`` (tests) returns None after that many chunks of this call, as if killed.
    """
    spec, = description.programs(name)
    raws = run_program(out, spec, description, resume, progress_fn, programs, stop_after_chunks)
    return None if raws is None else raws[name]


def run_program(out: str, spec: grids.ProgramSpec, description: RunDescription, resume: bool,
                progress_fn: ProgressReceiver = _silent, programs: Optional[Programs] = None,
                stop_after_chunks: Optional[int] = None) -> Optional[dict]:
    """Runs (or resumes) one program (``jcomps.runner.grid.programs``): its grid points × the seeds as one set of
    compiled programs; returns {entry key: RawResults} when the sequence is done. Events go to ``progress_fn``.

    Members are laid out by ``jcomps.runner.members.layout``. A member uses its seed's keys and (stationary) task order,
    whatever its grid point. ``programs`` holds the compiled programs (default: a fresh cache).
    ``stop_after_chunks`` (tests) returns None after that many chunks of this call, as if killed.
    """
    job = _ProgramRun(out, spec, description, progress_fn, Programs() if programs is None else programs)
    states = job.open(resume)
    job.method_program.receiver = job.receive
    try:
        for chunks_run, c in enumerate(range(job.next_chunk, job.num_chunks), 1):
            states = job.run_chunk(states, c)
            if stop_after_chunks is not None and chunks_run >= stop_after_chunks and c + 1 < job.num_chunks:
                return None
    finally:
        job.method_program.receiver = None
    return job.finish()


def to_host(tree):
    """``tree``'s arrays as NumPy arrays, on every process (``jcomps.runner.distributed.gather``: with several processes
    one all-gather). An empty array sharded over several devices (e.g. no backward-transfer tasks:
    [members, tasks, 0]) is made on the host: jax 0.10's ``device_get`` of one fails to assemble it."""
    return distributed.gather(tree)


class _ProgramRun:
    """One program's run (``run_program``): the loop over its chunks, with what stays fixed while it runs (its
    members, its compiled programs bound to their inputs), the host copies of its metrics (``metrics``, a
    ``_HostMetrics`` made once the learning program is compiled), its checkpoints and its events."""

    def __init__(self, out: str, spec: grids.ProgramSpec, description: RunDescription, progress_fn: ProgressReceiver,
                 programs: Programs):
        run = description.run
        self.out, self.spec, self.run, self.progress_fn = out, spec, run, progress_fn
        self.family, self.eval_config, self.points = description.family, description.eval, spec.points
        real = len(self.points) * run.seeds
        self.devices = num_devices(real)
        self.member_point, self.member_seed, self.hparams_host = layout(spec, run.seeds, run.seed, self.devices)
        self.padding = len(self.member_seed) - real
        self.method_program = programs.get(spec.method, run.family, spec.config, self.eval_config,
                                           min(run.chunk_tasks, run.num_tasks), self.devices, spec.traced)
        self.program = self.method_program.bind(
            task_sequences(self.family, run.sequence, self.member_seed, run.num_tasks, run.tasks),
            np.arange(len(self.member_seed), dtype=np.int32), task_eval_keys(self.member_seed), self.hparams_host,
            jax.device_get(envs.held_out(self.family)))  # host arrays: the same on every process
        self.chunk = self.method_program.chunk
        self.name = self.points[0].key if len(self.points) == 1 else f"{spec.label}, {len(self.points)} grid points"
        self.init_keys = method_keys(self.member_seed)
        self.num_chunks = math.ceil(run.num_tasks / self.chunk)
        # The tasks learnt at each measurement (``_HostMetrics.heldout``).
        self.after_tasks = np.asarray([min(c * self.chunk, run.num_tasks) for c in range(self.num_chunks + 1)],
                                      np.int64)
        self.checkpoints = Checkpoints(os.path.join(out, "checkpoints", spec.directory))
        self.next_chunk, self.seconds, self.started = 0, 0.0, time.time()

    def receive(self, metrics: dict):
        """The compiled programs' progress (``jcomps.progress``), as member events (``events.member_event``)."""
        self.progress_fn(events.member_event(self.name, metrics))

    def ensure_compiled(self, part: str, states):
        """Compiles ``part`` of the program for ``states`` and the run's inputs unless done, saying so
        (``events.Compiling``, ``events.StillCompiling`` while it takes, ``events.Compiled``)."""
        if part in self.method_program.compiled:
            return
        where = dict(program=self.name, family=self.run.family, method=self.spec.method, part=part,
                     what=PART_NAMES[part])
        self.progress_fn(events.Compiling(**where))
        times = self.method_program.compile(
            part, *self.program.arguments(part, states),
            waiting=lambda seconds: self.progress_fn(events.StillCompiling(**where, seconds=seconds)))
        self.progress_fn(events.Compiled(**where, **times._asdict()))

    def open(self, resume: bool):
        """The members' states to continue from: the initial ones (the learning program compiled for them), or
        with ``resume`` those of the newest readable checkpoint, with the metrics so far and ``next_chunk``."""
        run = self.run
        self.progress_fn(events.Start(
            program=self.name, family=run.family, sequence=run.sequence, num_tasks=run.num_tasks,
            tasks=tuple(run.tasks), seeds=run.seeds, grid_points=len(self.points), padding=self.padding,
            devices=self.devices, budget=methods.collection(self.spec.config).budget_for(self.family),
            chunk=self.chunk, start_task=0,
            members=tuple(f"{self.points[p].key} seed {s}" for p, s in zip(self.member_point, self.member_seed))))
        states = self.method_program.init(self.init_keys, self.hparams_host)
        # The learning program is the one a run waits for: it compiles first, alone.
        self.ensure_compiled("learn", states)
        num_heldout = jax.tree.leaves(self.program.inputs.heldout_tasks)[0].shape[0]
        self.metrics = _HostMetrics(self.method_program.compiled["learn"].out_info[1], self.eval_config,
                                    len(self.member_seed), num_heldout, self.after_tasks, self.points, run.seeds)
        if resume:
            states = self._restore(states)
        # A run stopped by older code has no partial results yet.
        if 0 < self.next_chunk < self.num_chunks and distributed.is_writer():
            for key, raw in self.metrics.raws(self.next_chunk, self.seconds, self.devices).items():
                results.save_partial(self.out, key, raw)
        self.started = time.time()
        return states

    def _restore(self, states):
        """The states of the newest readable checkpoint (``states`` when there is none), its metrics restored."""
        warn = lambda message: self.progress_fn(events.Warned(message))  # noqa: E731
        m = self.metrics
        restored = self.checkpoints.restore_latest(record(states, m.per_task, m.heldout, 0, 0.0), warn)
        if restored is None:
            return states
        step, tree = restored
        states = self.method_program.put(unflatten(states, tree["states"]))
        m.per_task, m.heldout = unflatten(m.per_task, tree["per_task"]), unflatten(m.heldout, tree["heldout"])
        self.next_chunk, self.seconds = int(tree["counters"]["next_chunk"]), float(tree["counters"]["seconds"])
        self.progress_fn(events.Resumed(self.name, step=step, num_tasks=self.run.num_tasks,
                                        tasks_done=min(self.next_chunk * self.chunk, self.run.num_tasks)))
        return states

    def elapsed(self) -> float:
        """Seconds the program has run, over every process that ran it."""
        return self.seconds + time.time() - self.started

    def run_chunk(self, states, c: int):
        """Learns chunk ``c``, evaluates it, checkpoints and reports it; returns the states after it. Each task is
        evaluated right after it is learnt; the evaluation programs compile while the first task trains."""
        start = c * self.chunk
        stop = min(start + self.chunk, self.run.num_tasks)

        def compile_evaluations(states):  # dispatched without waiting: these compile while the task trains
            self.ensure_compiled("evaluate_task", states)
            self.ensure_compiled("measure", states)

        states, metrics = self.program.learn_chunk(states, start, stop, after_learn=compile_evaluations)
        metrics = to_host(metrics)
        jax.tree.map(lambda dst, src: dst.__setitem__((slice(None), slice(start, stop)), src), self.metrics.per_task,
                     metrics)
        if c == 0:
            # The held-out meta-test of the initial policies (0 tasks learnt): the same states and keys as
            # before training, measured after the first chunk, off the path to the first iteration.
            initial = self.method_program.init(self.init_keys, self.hparams_host)
            self.evaluate(initial, 0, 0, heldout_keys(self.member_seed, 0), 0)
        # The learnt tasks after every chunk, or (learnt_eval=end) after the last one only.
        learnt = stop if self.eval_config.learnt_eval == "chunk" or stop == self.run.num_tasks else 0
        learnt_now = self.evaluate(states, c + 1, learnt, heldout_keys(self.member_seed, c + 1), stop).learnt
        self.save(states, c + 1)
        for event in self.metrics.chunk_events(self.name, start, stop, metrics, learnt_now, self.run.seed):
            self.progress_fn(event)
        return states

    def evaluate(self, states, column: int, learnt: int, keys, after: int):
        """The evaluations of ``states`` (``learnt``: the tasks to evaluate) into column ``column`` of ``heldout``
        (``after``: the tasks learnt, for the progress lines); returns them on the host."""
        self.ensure_compiled("measure", states)
        self.progress_fn(events.Evaluating(self.name, after, learnt, adapts=self.eval_config.heldout_measured))
        began = time.time()
        out = to_host(self.program.measure(states, keys, learnt))
        jax.tree.map(lambda dst, src: dst.__setitem__((slice(None), column), src), self.metrics.heldout, out)
        self.progress_fn(events.Evaluated(self.name, after, seconds=time.time() - began))
        return out

    def save(self, states, chunks_done: int):
        """Checkpoints the run after ``chunks_done`` chunks, and the partial results of an unfinished one (what
        ``report.py --partial`` shows)."""
        elapsed = self.elapsed()
        self.checkpoints.save(chunks_done, record(states, self.metrics.per_task, self.metrics.heldout, chunks_done,
                                                  elapsed))
        if chunks_done < self.num_chunks and distributed.is_writer():
            for key, raw in self.metrics.raws(chunks_done, elapsed, self.devices).items():
                results.save_partial(self.out, key, raw)

    def finish(self) -> dict:
        """Writes every entry's results once the sequence is done; returns them ({entry key: RawResults})."""
        total = self.elapsed()
        raws = self.metrics.raws(self.num_chunks, total, self.devices)
        if distributed.is_writer():
            for key, raw in raws.items():
                results.save(self.out, key, raw)
        self.progress_fn(events.Done(self.name, seconds=total))
        return raws


class _HostMetrics:
    """The host copies of one program's metrics over the sequence, zeroed at first and filled as it runs:
    ``per_task``, ChunkMetrics [members, num_tasks, ...], task by task; ``heldout``, the ``continual.Measurement``
    [members, num_chunks + 1, ...], at the start and after every chunk (``after_tasks``: the tasks learnt at each
    measurement); and the results entries they make (``points``, each ``seeds`` members; padding members are
    dropped)."""

    def __init__(self, task_shapes, eval_config: continual.EvalConfig, members: int, num_heldout: int,
                 after_tasks: np.ndarray, points, seeds: int):
        num_tasks, measurements = int(after_tasks[-1]), len(after_tasks)
        member = lambda shapes: jax.tree.map(  # noqa: E731
            lambda x: jax.ShapeDtypeStruct((members,) + x.shape, x.dtype), shapes)
        chunk_shapes = continual.chunk_metrics(task_shapes, member(continual.task_evaluation_shapes(eval_config)))
        heldout_shapes = member(continual.heldout_shapes(eval_config, num_heldout, num_tasks))
        self.per_task = jax.tree.map(lambda x: np.zeros((x.shape[0], num_tasks) + x.shape[1:], x.dtype),
                                     chunk_shapes)
        self.heldout = jax.tree.map(lambda x: np.zeros((x.shape[0], measurements) + x.shape[1:], x.dtype),
                                    heldout_shapes)
        self.after_tasks = after_tasks
        self.slices = {point.key: (slice(p * seeds, (p + 1) * seeds),) for p, point in enumerate(points)}

    def entries(self):
        """(entry key, the index of its members) of every results entry."""
        return self.slices.items()

    def chunk_events(self, program: str, start: int, stop: int, metrics, learnt_now, first_seed: int) -> list:
        """The ``events.Chunk`` of every results entry of ``program`` (``metrics``: the chunk's ChunkMetrics,
        ``learnt_now``: the learnt tasks' Evaluation after it, both [members, ...])."""
        num_tasks = int(self.after_tasks[-1])
        out = []
        for key, mine in self.entries():
            seeds = tuple(range(first_seed, first_seed + mine[0].stop - mine[0].start))
            out.append(events.Chunk(program, key, start=start, stop=stop, num_tasks=num_tasks, seeds=seeds,
                                    metrics=jax.tree.map(lambda x: np.asarray(x)[mine], metrics),
                                    per_task=jax.tree.map(lambda x: x[mine], self.per_task),
                                    learnt_tasks=jax.tree.map(lambda x: np.asarray(x)[mine], learnt_now)))
        return out

    def raws(self, chunks_done: int, seconds: float, devices: int) -> dict:
        """{entry key: RawResults} of the tasks of the first ``chunks_done`` chunks."""
        upto, measured = int(self.after_tasks[chunks_done]), chunks_done + 1
        raws = {}
        for key, mine in self.entries():
            task = jax.tree.map(lambda x: np.asarray(x[mine][:, :upto]), self.per_task)
            held = jax.tree.map(lambda x: np.asarray(x[mine][:, :measured]), self.heldout.heldout)
            learnt = jax.tree.map(lambda x: np.asarray(x[mine][:, :measured, :upto]), self.heldout.learnt)
            raws[key] = results.RawResults(per_task=task, measured=continual.Measurement(held, learnt),
                                           heldout_after_tasks=self.after_tasks[:measured], seconds=float(seconds),
                                           devices=int(devices))
        return raws
