"""Experiment runs: methods over a task sequence, seeds sharded over devices, chunked, checkpointed, resumable.

A run directory holds:

- ``run.json``: everything that defines the run (``jcomps.rundir``); a resume must match it.
- ``checkpoints/<program>/<step>/``: checkpoints (``jcomps.checkpoint``) of a program's entire state
  (parameters, optimiser states, experience stores, rng, counters) and the metrics so far, written after every
  chunk of tasks. A program is a method (``checkpoints/<method>``), or with a grid one per combination of its
  shape-changing values (``checkpoints/<method>@hidden_sizes=64x32``).
- ``raw/<entry>.npz``: all metrics of a results entry (a method, or a method at a grid point) once its program
  is done: a ``jcomps.results.RawResults``, the input of ``jcomps.report``. Until then
  ``raw/partial/<entry>.npz`` holds the tasks finished so far, rewritten after every chunk
  (``report.py --partial`` reports a stopped run from them).
- ``results.json``, ``plots/*.png``, ``significance.md``: written by ``jcomps.report`` at the end.

Here is the host loop. A program's members (``jcomps.members``: the seeds, or a grid's points × the seeds) run
through its compiled programs (``jcomps.programs``): the host loops over the tasks of a chunk (``learn``, then
``evaluate_task``), evaluates after the chunk (``heldout``) and checkpoints; since every chunk runs through the
same programs from the restored state, a resumed run gives per-task results identical to an uninterrupted one.

Nothing here prints: the outside world gets events through one ``progress_fn`` callback (``ProgressReceiver``;
``experiments/progress.py`` turns them into progress lines and TensorBoard logs). Compiled programs live in a
``Programs`` cache owned by the caller, never in a module-level registry, so two runs never share progress.
``RunError`` (``jcomps.checkpoint``) is what ``run`` raises for a run directory it cannot make or resume.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from typing import Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np

from jcomps import continual, envs, grid as grids, methods, progress, results
from jcomps.checkpoint import Checkpoints, RunError, record, unflatten  # noqa: F401 - RunError: what run raises
from jcomps.members import eval_keys, layout, method_keys, num_devices
from jcomps.numerics import check_field, check_finite_fields
from jcomps.programs import PART_NAMES, Programs
from jcomps.rundir import describe, open_run_dir


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """What a run learns: the family, the sequence, the methods and the seeds."""

    family: str = "point_goal"
    """Task family (see ``jcomps.envs.FAMILIES``)."""
    sequence: str = "non-stationary"
    """``non-stationary`` (the paper's order) or ``stationary`` (the same list shuffled by seed)."""
    methods: tuple[str, ...] = ("comps", "ppo_tl")
    """Methods to run, one compiled program each."""
    seeds: int = 4
    """Number of seeds (a vmap axis, sharded over devices)."""
    seed: int = 0
    """The first seed; seeds are seed, seed + 1, ..."""
    num_tasks: int = 6
    """Length of the sequence (a prefix of the family's list, shuffled per seed if stationary)."""
    chunk_tasks: int = 2
    """Tasks per compiled chunk; a checkpoint is written after every chunk."""

    def __post_init__(self):
        check_finite_fields(self)
        check_field(self.family in envs.FAMILIES, "family", self.family, ", ".join(envs.FAMILIES))
        check_field(self.sequence in envs.SEQUENCE_KINDS, "sequence", self.sequence, ", ".join(envs.SEQUENCE_KINDS))
        check_field(len(self.methods) >= 1 and len(set(self.methods)) == len(self.methods), "methods", self.methods,
                    "one or more distinct method names")
        for name in self.methods:
            check_field(name in methods.METHODS, "methods", name, ", ".join(methods.METHODS))
        check_field(self.seeds >= 1, "seeds", self.seeds, "an integer >= 1")
        check_field(self.seed >= 0, "seed", self.seed, "an integer >= 0")
        check_field(self.num_tasks >= 1, "num_tasks", self.num_tasks, "an integer >= 1")
        check_field(self.chunk_tasks >= 1, "chunk_tasks", self.chunk_tasks, "an integer >= 1")


# The kinds of event the runner hands its ``ProgressReceiver`` (``event["event"]``); ``ProgressReceiver`` says
# what each carries. The runner's own:
START = "start"
COMPILING = "compiling"
STILL_COMPILING = "still_compiling"
COMPILED = "compiled"
RESUMED = "resumed"
WARNING = "warning"
EVALUATING = "evaluating"
EVALUATED = "evaluated"
CHUNK = "chunk"
DONE = "done"
SKIPPED = "skipped"
# and the compiled programs' progress, passed on with its phase as the kind (``jcomps.progress``):
ITERATION, META_STEP, COMPRESS_ITERATION = progress.ITERATION, progress.META_STEP, progress.COMPRESS_ITERATION
HELDOUT_ITERATION, TASK = progress.HELDOUT_ITERATION, progress.TASK
EVENTS = (START, COMPILING, STILL_COMPILING, COMPILED, RESUMED, WARNING, EVALUATING, EVALUATED, CHUNK, DONE, SKIPPED,
          *progress.PHASES)
"""Every kind of event."""

ProgressReceiver = Callable[[dict], None]
"""The runner's one callback to the outside world (brax's ``progress_fn``), called on the host with an event dict;
``event["event"]`` says which (``EVENTS``):

- ``START``: a program begins, before anything compiles (``program``, ``family``, ``sequence``, ``num_tasks``,
  ``seeds``, ``grid_points``, ``padding``, ``devices``, ``budget``, ``chunk``, ``start_task``: 0, ``members``:
  each member's name);
- ``COMPILING`` / ``COMPILED``: one of its programs (``jcomps.programs.PARTS``) is being compiled / is ready
  (``program``, ``family``, ``method``, ``part``, ``what``: its name in words; ``COMPILED`` adds ``seconds``,
  ``trace_seconds`` and ``cached``: whether it came from the persistent compile cache, ``jcomps.compile_cache``);
  a compile still running says so every ``jcomps.programs.HEARTBEAT_SECONDS`` with ``STILL_COMPILING`` (the same
  fields and the ``seconds`` so far); ``learn`` compiles first and alone, the evaluation programs while the first
  task trains;
- ``RESUMED``: it continues from a checkpoint (``program``, ``step``, ``tasks_done``, ``num_tasks``);
- ``EVALUATING`` / ``EVALUATED``: the held-out meta-test and learnt-task evaluation after ``after_tasks`` tasks
  (0: the initial policies, measured after the first chunk) begins (``learnt``: how many learnt tasks it
  evaluates) / ends (``seconds``); in between, ``HELDOUT_ITERATION`` events give each member's adaptation progress
  (``member``, ``heldout_task``, ``heldout_iteration``, ``success_rate``, ``mean_return``);
- ``WARNING``: something was set aside (``message``), e.g. an unreadable checkpoint;
- ``ITERATION`` / ``META_STEP``: a member's progress inside a chunk (``program``, ``member``, ``task`` and the
  ``jcomps.progress`` metrics: ``iteration``, ``success_rate``, ``mean_return`` / ``meta_step``,
  ``meta_steps``, ``bc_loss``, ``value_l2``, ``value_ev``, ``adv_abs``, ``rho``);
- ``COMPRESS_ITERATION``: the same for a compress phase of ``pnc`` (``compress_iteration``,
  ``compress_iterations``, ``kl``);
- ``CHUNK``: a chunk of tasks is done, per results entry (``program``, ``entry``, ``start``, ``stop``,
  ``num_tasks``, ``seeds``, ``metrics``: its members' ChunkMetrics, ``per_task``: every task's so far,
  ``learnt_tasks``: the Evaluation [members, num_tasks] of every task learnt, valid False where not evaluated),
  after the checkpoint is written;
- ``DONE``: the program finished (``program``, ``seconds``); ``SKIPPED``: it had finished before (``program``).
"""


def _silent(event: dict) -> None:
    del event


def run_method(out: str, name: str, run: RunConfig, eval_config: continual.EvalConfig, config, resume: bool,
               progress_fn: ProgressReceiver = _silent, programs: Optional[Programs] = None,
               stop_after_chunks: Optional[int] = None) -> Optional[results.RawResults]:
    """Runs (or resumes) one method's sequence, without a grid; returns its raw results when the sequence is
    done.

    ``stop_after_chunks`` (tests) returns None after that many chunks of this call, as if killed.
    """
    spec, = grids.programs(name, config, ())
    raws = run_program(out, spec, run, eval_config, resume, progress_fn, programs, stop_after_chunks)
    return None if raws is None else raws[name]


def run_program(out: str, spec: grids.ProgramSpec, run: RunConfig, eval_config: continual.EvalConfig, resume: bool,
                progress_fn: ProgressReceiver = _silent, programs: Optional[Programs] = None,
                stop_after_chunks: Optional[int] = None) -> Optional[dict]:
    """Runs (or resumes) one program (``jcomps.grid.programs``): its grid points × the seeds as one compiled
    chunk program; returns {entry key: RawResults} when the sequence is done. Events go to ``progress_fn``.

    Members are laid out by ``jcomps.members.layout``. A member uses its seed's keys and (stationary) task order,
    whatever its grid point. ``programs`` holds the compiled programs (default: a fresh cache).
    ``stop_after_chunks`` (tests) returns None after that many chunks of this call, as if killed.
    """
    family = envs.make(run.family)
    eval_config = eval_config.resolve(run.family)
    points = spec.points
    real = len(points) * run.seeds
    devices = num_devices(real)
    member_point, member_seed, hparams_host = layout(spec, run.seeds, run.seed, devices)
    padded = len(member_seed)
    programs = Programs() if programs is None else programs
    program = programs.get(spec.method, run.family, spec.config, eval_config, min(run.chunk_tasks, run.num_tasks),
                           devices, spec.traced)
    hparams = program.put(hparams_host)
    name = points[0].key if len(points) == 1 else f"{spec.label}, {len(points)} grid points"

    orders = {s: envs.sequence_values(family, run.sequence, s, run.num_tasks) for s in sorted(set(member_seed))}
    values = np.stack([orders[s] for s in member_seed])
    sequences = jax.tree.map(lambda x: x.reshape((padded, run.num_tasks) + x.shape[1:]),
                             family.tasks(values.reshape(-1)))
    sequences = program.put(sequences)
    heldout_tasks = envs.held_out(family)
    seed_index = program.put(np.arange(padded, dtype=np.int32))
    backward_keys = program.put(eval_keys(member_seed, 1))
    num_chunks = math.ceil(run.num_tasks / program.chunk)

    def compile_part(part: str, *args):
        """Compiles ``part`` of the program for ``args`` unless done, saying so (``COMPILING``, ``STILL_COMPILING``
        while it takes, ``COMPILED``)."""
        if part in program.compiled:
            return
        where = {"program": name, "family": run.family, "method": spec.method, "part": part, "what": PART_NAMES[part]}
        progress_fn({"event": COMPILING, **where})
        times = program.compile(part, *args, waiting=lambda seconds: progress_fn({"event": STILL_COMPILING, **where,
                                                                                   "seconds": seconds}))
        progress_fn({"event": COMPILED, **where, **times._asdict()})

    member_names = [f"{points[p].key} seed {s}" for p, s in zip(member_point, member_seed)]
    progress_fn({"event": START, "program": name, "family": run.family, "sequence": run.sequence,
                 "num_tasks": run.num_tasks, "seeds": run.seeds, "grid_points": len(points), "padding": padded - real,
                 "devices": devices, "budget": methods.collection(spec.config).budget_for(family),
                 "chunk": program.chunk, "start_task": 0, "members": member_names})
    init_keys = method_keys(member_seed)
    states = program.init(init_keys, hparams_host)
    # The learning program is the one a run waits for: it compiles first, alone.
    compile_part("learn", states, sequences, np.int32(0), seed_index, hparams)
    task_shapes = program.compiled["learn"].out_info[1]
    member = lambda shapes: jax.tree.map(  # noqa: E731
        lambda x: jax.ShapeDtypeStruct((padded,) + x.shape, x.dtype), shapes)
    chunk_shapes = continual.chunk_metrics(task_shapes, member(continual.task_evaluation_shapes(eval_config)))
    num_heldout = jax.tree.leaves(heldout_tasks)[0].shape[0]
    heldout_shapes = member(continual.heldout_shapes(eval_config, num_heldout, run.num_tasks))
    # Host copies of every metric of the sequence, filled task by task: [members, num_tasks, ...]; those measured
    # at the start and after every chunk (held-out adaptation, learnt tasks): [members, num_chunks + 1, ...].
    per_task = jax.tree.map(lambda x: np.zeros((x.shape[0], run.num_tasks) + x.shape[1:], x.dtype), chunk_shapes)
    heldout = jax.tree.map(lambda x: np.zeros((x.shape[0], num_chunks + 1) + x.shape[1:], x.dtype), heldout_shapes)

    checkpoints = Checkpoints(os.path.join(out, "checkpoints", spec.directory))
    next_chunk, seconds = 0, 0.0
    if resume:
        warn = lambda message: progress_fn({"event": WARNING, "message": message})  # noqa: E731
        restored = checkpoints.restore_latest(record(states, per_task, heldout, 0, 0.0), warn)
        if restored is not None:
            step, tree = restored
            states = program.put(unflatten(states, tree["states"]))
            per_task = unflatten(per_task, tree["per_task"])
            heldout = unflatten(heldout, tree["heldout"])
            next_chunk, seconds = int(tree["counters"]["next_chunk"]), float(tree["counters"]["seconds"])
            progress_fn({"event": RESUMED, "program": name, "step": step,
                         "tasks_done": min(next_chunk * program.chunk, run.num_tasks), "num_tasks": run.num_tasks})

    # The reported members of each point (padding members are dropped).
    slices = [(slice(p * run.seeds, (p + 1) * run.seeds),) for p in range(len(points))]
    after_tasks = np.asarray([min(c * program.chunk, run.num_tasks) for c in range(num_chunks + 1)], np.int64)

    def entry_raws(chunks_done: int, seconds_: float) -> dict:
        """{entry key: RawResults} of the tasks of the first ``chunks_done`` chunks."""
        upto, measured = int(after_tasks[chunks_done]), chunks_done + 1
        raws_ = {}
        for p, point in enumerate(points):
            task = jax.tree.map(lambda x: np.asarray(x[slices[p]][:, :upto]), per_task)
            held = jax.tree.map(lambda x: np.asarray(x[slices[p]][:, :measured]), heldout[0])
            learnt = jax.tree.map(lambda x: np.asarray(x[slices[p]][:, :measured, :upto]), heldout[1])
            raws_[point.key] = results.RawResults(task.task, task.backward_returns, task.backward_valid, held,
                                                  after_tasks[:measured], float(seconds_), int(devices),
                                                  task.backward_success, task.learnt, learnt)
        return raws_

    if 0 < next_chunk < num_chunks:  # a run stopped by older code has no partial results yet
        for key, raw in entry_raws(next_chunk, seconds).items():
            results.save_partial(out, key, raw)

    start_time = time.time()
    def compile_heldout(states):
        """The held-out program, compiled for arguments shaped as ``evaluate`` gives them (a no-op once done)."""
        compile_part("heldout", states, heldout_tasks, backward_keys, sequences, np.int32(0), backward_keys,
                     seed_index, hparams)

    def evaluate(states, column: int, learnt: int, keys, after: int):
        """The evaluations of ``states`` (``learnt``: the tasks to evaluate) into column ``column`` of ``heldout``
        (``after``: the tasks learnt, for the progress lines)."""
        compile_heldout(states)
        progress_fn({"event": EVALUATING, "program": name, "after_tasks": after, "learnt": learnt})
        began = time.time()
        out_h = jax.device_get(program.heldout(states, heldout_tasks, program.put(keys), sequences, np.int32(learnt),
                                               backward_keys, seed_index, hparams))
        jax.tree.map(lambda dst, src: dst.__setitem__((slice(None), column), np.asarray(src)), heldout, out_h)
        progress_fn({"event": EVALUATED, "program": name, "after_tasks": after, "seconds": time.time() - began})
        return out_h

    def receive(metrics: dict):
        progress_fn({"event": metrics["phase"], "program": name,
                     **{k: v.item() for k, v in metrics.items() if k != "phase"}})

    seeds = list(range(run.seed, run.seed + run.seeds))
    chunks_run = 0
    program.receiver = receive
    try:
        for c in range(next_chunk, num_chunks):
            start = c * program.chunk
            stop = min(start + program.chunk, run.num_tasks)
            task_metrics = []
            for i in range(start, stop):
                states, learnt_metrics = program.learn(states, sequences, np.int32(i), seed_index, hparams)
                # Dispatched without waiting: the evaluation programs compile while the task trains.
                compile_part("evaluate_task", states, sequences, np.int32(i), backward_keys, hparams)
                evaluation = program.evaluate_task(states, sequences, np.int32(i), backward_keys, hparams)
                compile_heldout(states)
                task_metrics.append(continual.chunk_metrics(learnt_metrics, evaluation))
            metrics = jax.device_get(jax.tree.map(lambda *x: jnp.stack(x, axis=1), *task_metrics))
            jax.tree.map(lambda dst, src: dst.__setitem__((slice(None), slice(start, stop)), src), per_task, metrics)
            if c == 0:
                # The held-out meta-test of the initial policies (0 tasks learnt): the same states and keys as
                # before training, measured after the first chunk, off the path to the first iteration.
                evaluate(program.init(init_keys, hparams_host), 0, 0, eval_keys(member_seed, 1000), 0)
            # The learnt tasks after every chunk, or (learnt_eval=end) after the last one only.
            learnt = stop if eval_config.learnt_eval == "chunk" or stop == run.num_tasks else 0
            _, learnt_now = evaluate(states, c + 1, learnt, eval_keys(member_seed, 1001 + c), stop)
            elapsed = seconds + time.time() - start_time
            checkpoints.save(c + 1, record(states, per_task, heldout, c + 1, elapsed))
            if c + 1 < num_chunks:  # what a report of the unfinished run shows (report.py --partial)
                for key, raw in entry_raws(c + 1, elapsed).items():
                    results.save_partial(out, key, raw)
            for p, point in enumerate(points):
                progress_fn({"event": CHUNK, "program": name, "entry": point.key, "start": start, "stop": stop,
                             "num_tasks": run.num_tasks, "seeds": seeds,
                             "metrics": jax.tree.map(lambda x: np.asarray(x)[slices[p]], metrics),
                             "per_task": jax.tree.map(lambda x: x[slices[p]], per_task),
                             "learnt_tasks": jax.tree.map(lambda x: np.asarray(x)[slices[p]], learnt_now)})
            chunks_run += 1
            if stop_after_chunks is not None and chunks_run >= stop_after_chunks and c + 1 < num_chunks:
                return None
    finally:
        program.receiver = None
    total = seconds + time.time() - start_time
    raws = entry_raws(num_chunks, total)
    for key, raw in raws.items():
        results.save(out, key, raw)
    progress_fn({"event": DONE, "program": name, "seconds": total})
    return raws


def run(out: str, run_config: RunConfig, eval_config: continual.EvalConfig, method_configs: dict,
        resume: bool = False, progress_fn: ProgressReceiver = _silent, grid: grids.Grid = (),
        overrides: Optional[dict] = None, programs: Optional[Programs] = None) -> dict:
    """Runs every method of ``run_config`` into ``out`` (resuming where it stopped), each at every point of the
    hyperparameter ``grid`` (``jcomps.grid``; empty: no grid); returns RawResults by results entry key. Events go
    to ``progress_fn`` (``ProgressReceiver``); compiled programs are kept in ``programs`` (default: a fresh cache)."""
    eval_config = eval_config.resolve(run_config.family)
    open_run_dir(out, describe(run_config, eval_config, method_configs, grid, overrides), resume)
    programs = Programs() if programs is None else programs
    raws = {}
    for name in run_config.methods:
        for spec in grids.programs(name, method_configs[name], grid):
            done = {p.key: results.load(out, p.key) for p in spec.points} if resume else {}
            if done and all(raw is not None for raw in done.values()):
                progress_fn({"event": SKIPPED, "program": spec.label})
            else:
                done = run_program(out, spec, run_config, eval_config, resume, progress_fn, programs)
            raws.update(done)
    return raws
