"""Experiment runs: methods over a task sequence, seeds sharded over devices, chunked, checkpointed, resumable.

A run directory holds:

- ``run.json``: everything that defines the run (run options, evaluation options, every method's config, the
  hyperparameter grid and the per-method ``--set`` overrides if any); a resume must match it.
- ``checkpoints/<program>/<step>/``: checkpoints (``jcomps.checkpoint``) of a program's entire state
  (parameters, optimiser states, experience stores, rng, counters) and the metrics so far, written after every
  chunk of tasks. A program is a method (``checkpoints/<method>``), or with a grid one per combination of its
  shape-changing values (``checkpoints/<method>@hidden_sizes=64x32``).
- ``raw/<entry>.npz``: all metrics of a results entry (a method, or a method at a grid point) once its program
  is done: a ``jcomps.results.RawResults``, the input of ``jcomps.report``. Until then
  ``raw/partial/<entry>.npz`` holds the tasks finished so far, rewritten after every chunk
  (``report.py --partial`` reports a stopped run from them).
- ``results.json``, ``plots/*.png``, ``significance.md``: written by ``jcomps.report`` at the end.

Per program there is one compiled chunk program: ``vmap`` over the members of a device, ``shard_map`` over
devices (the member axis), a ``lax.scan`` over ``chunk_tasks`` tasks. Members are the seeds, or with a grid
(``jcomps.grid``) the program's grid points × the seeds, point-major; traced hyperparameters enter as one
scalar per member, and the method is made inside the traced function from a config holding it. The host loops
over chunks and checkpoints between them; since every chunk runs through the same program from the restored
state, a resumed run gives per-task results identical to an uninterrupted one.

Nothing here prints: the outside world gets events through one ``progress_fn`` callback (``ProgressReceiver``;
``experiments/progress.py`` turns them into progress lines and TensorBoard logs). Compiled programs live in a
``Programs`` cache owned by the caller, never in a module-level registry, so two runs never share progress.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import threading
import time
from typing import Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import PartitionSpec as P

from jcomps import compile_cache, continual, envs, grid as grids, methods, progress, results
from jcomps.checkpoint import Checkpoints, RunError, record, unflatten
from jcomps.numerics import check_field, check_finite_fields
from jcomps.rundir import write_json


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


def _jsonable(x):
    if dataclasses.is_dataclass(x):
        return {f.name: _jsonable(getattr(x, f.name)) for f in dataclasses.fields(x)}
    if isinstance(x, (tuple, list)):
        return [_jsonable(v) for v in x]
    return x


def describe(run: RunConfig, eval_config: continual.EvalConfig, method_configs: dict, grid=(),
             overrides: Optional[dict] = None) -> dict:
    """The JSON description of a run (``run.json``), with this process's device count: float rounding depends on
    it, so a resume must use the same count (``experiments/run_sequence.py --resume`` takes it from here). With a
    hyperparameter grid, ``grid`` holds its axes in order (``jcomps.grid.to_json``); with per-method overrides
    (``--set``), ``overrides`` holds them ({method: {"field.path": value}}, already part of the methods' configs);
    without either there is no such key."""
    out = {"run": _jsonable(run), "eval": _jsonable(eval_config),
           "methods": {name: _jsonable(method_configs[name]) for name in run.methods},
           "devices": jax.device_count()}
    if grid:
        out["grid"] = grids.to_json(grid)
    if overrides:
        out["overrides"] = {m: {k: _jsonable(v) for k, v in values.items()} for m, values in overrides.items()}
    return out


def _differences(a, b, prefix="") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for key in sorted(set(a) | set(b)):
            out += _differences(a.get(key), b.get(key), f"{prefix}{key}.")
        return out
    return [] if a == b else [f"{prefix[:-1]}: run has {a!r}, asked {b!r}"]


# Config fields whose addition changed what a method's state holds, so that a run made before them cannot be
# resumed by this version whatever the options (its checkpoints no longer fit): field path within a method's
# config -> why.
UNRESUMABLE_BEFORE = {
    "meta.value_init": "CoMPS's meta step now keeps one value network per task and starts a new task's from the RL "
                       "step's critic (issue 27)",
    "context_source": "PEARL now keeps oyster's encoder buffers and weighs its KL per task (issue 28)",
    "kb_statistics": "PNC's knowledge base now pools its observation statistics over tasks (issue 28)",
}


def _fill_added_fields(stored: dict, asked: dict, default: dict, prefix: str) -> list[str]:
    """Config fields that a stored run lacks because jcomps added them after the run was made: where the asked
    value is the field's default (the behaviour the run had, as every added field keeps the old behaviour by
    default), ``stored`` gets it, in place. Returns the dotted paths filled; other differences are left for
    :func:`_differences` to report."""
    filled = []
    for key, value in asked.items():
        if not isinstance(default, dict) or key not in default:
            continue
        if key not in stored:
            in_method = prefix.startswith("methods.")
            path = prefix.split(".", 2)[-1] + key if in_method else prefix + key
            why = (UNRESUMABLE_BEFORE if in_method else UNRESUMABLE_EVAL_BEFORE).get(path)
            if why is not None:
                raise RunError(f"--resume: this run was made before {prefix}{key} existed and cannot be resumed by "
                               f"this version ({why}); start it anew with another --out")
            if value == default[key]:
                stored[key] = value
                filled.append(prefix + key)
        elif isinstance(stored[key], dict) and isinstance(value, dict):
            filled += _fill_added_fields(stored[key], value, default[key], f"{prefix}{key}.")
    return filled


# The same for evaluation fields (``eval.<field>``), whose addition changed the metrics that checkpoints hold.
UNRESUMABLE_EVAL_BEFORE = dict.fromkeys(
    ("eval.learnt_eval", "eval.learnt_episodes"),
    "its checkpoints lack the evaluations of the learnt tasks behind forgetting and average performance (issue 28)")


def open_run_dir(out: str, description: dict, resume: bool) -> None:
    """Creates ``out`` for a new run, or checks that it holds this very run when resuming."""
    run_json = os.path.join(out, "run.json")
    if resume:
        if not os.path.isfile(run_json):
            raise RunError(f"--resume: {out} holds no run (no run.json); start it without --resume")
        with open(run_json) as f:
            stored = json.load(f)
        filled = []
        for name, config in description.get("methods", {}).items():
            if isinstance(stored.get("methods", {}).get(name), dict):
                default = _jsonable(methods.default_config(name, description["run"]["family"]))
                filled += _fill_added_fields(stored["methods"][name], config, default, f"methods.{name}.")
        if isinstance(stored.get("eval"), dict) and isinstance(description.get("eval"), dict):
            filled += _fill_added_fields(stored["eval"], description["eval"], _jsonable(continual.EvalConfig()),
                                         "eval.")
        diff = _differences(stored, description)
        diff = [d + f" (float rounding depends on it: resume with --devices {stored['devices']})"
                if d.startswith("devices:") else d for d in diff]
        if diff:
            raise RunError(f"--resume: {out} was made with another config: " + "; ".join(diff[:8]))
        if filled:  # record them, so that the run's description is whole again
            write_json(run_json, stored)
        return
    if os.path.exists(run_json) or os.path.exists(os.path.join(out, "results.json")):
        raise RunError(f"{out} already holds a run; choose another --out, or add --resume to continue it")
    try:
        os.makedirs(out, exist_ok=True)
        write_json(run_json, description)
    except OSError as err:
        raise RunError(f"--out {out}: cannot create the run directory there ({type(err).__name__}: "
                       f"{err.strerror or err}); choose a writable path") from None


def num_devices(seeds: int, available: Optional[int] = None) -> int:
    """How many devices ``seeds`` seeds are spread over: all available ones, at most one per seed."""
    return max(1, min(seeds, available or jax.device_count()))


def padded_seeds(seeds: int, devices: int) -> int:
    """Seeds actually run: ``seeds`` rounded up to a multiple of ``devices`` (every device gets the same number;
    the extra seeds, run + ``seeds``, ..., cost no wall time and are dropped from the results)."""
    return -(-seeds // devices) * devices


# The method's and the evaluations' random streams come from separately salted roots of each seed's key. With
# jax's partitionable threefry ``fold_in(k, 1)`` equals ``split(k)[1]``, so evaluation keys folded from the
# method's own root could coincide with keys the method draws.
METHOD_SALT, EVAL_SALT = 0x6D657468, 0x6576616C  # "meth", "eval"


def _salted(seeds: list[int], *salts: int) -> jax.Array:
    """Each seed's key folded with ``salts`` in turn."""
    def one(seed):
        key = jax.random.PRNGKey(seed)
        for salt in salts:
            key = jax.random.fold_in(key, salt)
        return key

    return jax.vmap(one)(jnp.asarray(seeds, jnp.uint32))


def method_keys(seeds: list[int]) -> jax.Array:
    """Each seed's key for ``method.init`` (everything the method draws descends from it)."""
    return _salted(seeds, METHOD_SALT)


def eval_keys(seeds: list[int], purpose: int) -> jax.Array:
    """Each seed's key for the evaluation ``purpose`` (1: backward transfer and, folded with
    ``continual.LEARNT_SALT``, the learnt tasks' evaluations; 1000 + c: held-out after chunk c)."""
    return _salted(seeds, EVAL_SALT, purpose)


HEARTBEAT_SECONDS = 20.0
"""How often a compile that is still running says so (``compiling`` events with ``seconds``)."""


@contextlib.contextmanager
def _heartbeat(beat: Callable[[], None], interval: float = HEARTBEAT_SECONDS):
    """Calls ``beat`` every ``interval`` seconds from a thread while the block runs (XLA compiles without holding
    the GIL, so the thread gets to run)."""
    done = threading.Event()

    def loop():
        while not done.wait(interval):
            beat()

    thread = threading.Thread(target=loop, daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()


PARTS = ("init", "learn", "evaluate_task", "heldout")
"""The compiled programs of a method (``MethodProgram``), in the order a run first needs them."""

PART_NAMES = {"init": "init", "learn": "learning", "evaluate_task": "per-task evaluation",
              "heldout": "held-out meta-test and learnt-task evaluation"}
"""What each program is called in progress lines."""


class MethodProgram:
    """The compiled programs of one method, members sharded over the devices (``PARTS``):

    - ``init``: the members' initial states;
    - ``learn``: learns the task at one position of the sequence (``continual.learn_at``); the host loops over
      positions, one program for every task;
    - ``evaluate_task``: the evaluations right after a task is learnt (backward transfer, the learnt task itself:
      ``continual.evaluate_task``);
    - ``heldout``: after a chunk of tasks, the held-out adaptation and the learnt tasks' evaluation
      (``continual.learnt_tasks``).

    Each holds the simulator once at most, so that the program on the critical path (``learn``) compiles alone and
    the evaluation programs can compile while the first task trains (``compile``: ahead of time, timed).

    ``make(hparams, progress_fn)`` makes the method from one member's dict of traced hyperparameters (empty
    without traced grid axes) and progress hook; it runs inside each traced function, so every member learns, is
    initialised and is evaluated with its own values. Every program takes ``hparams``, a dict of f32[members]
    arrays (default: none). ``traces`` counts how often each program was traced (once each, however many tasks
    run). While a program runs, every member's progress metrics (``jcomps.progress``) reach ``receiver`` (a host
    function of one dict, set by whoever runs the program; None: dropped) with the member's index as ``member``.
    """

    def __init__(self, make: Callable[..., methods.Method], eval_config: continual.EvalConfig, chunk: int,
                 devices: int):
        self.make, self.chunk, self.eval_config = make, chunk, eval_config
        self.receiver: Optional[Callable[[dict], None]] = None
        self.traces: dict = dict.fromkeys(PARTS, 0)
        self.compiled: dict = {}
        """Part -> its ``jax.stages.Compiled``, once ``compile`` made it."""
        mesh = jax.make_mesh((devices,), ("seed",), devices=jax.devices()[:devices])
        seed = P("seed")

        def learn(states, sequences, i, seed_index, hparams):
            self.traces["learn"] += 1
            continual.check_capacity(make({}, None), jax.tree.leaves(sequences)[0].shape[1])

            def fn(s, q, m, h):
                # The hook closes over the member's (traced) index: the method reports its task, we add who it is.
                report = progress.host(self._receive)
                return continual.learn_at(make(h, progress.with_fields(report, member=m)), s, q, i)

            return jax.vmap(fn)(states, sequences, seed_index, hparams)

        def evaluate_task(states, sequences, i, eval_keys, hparams):
            self.traces["evaluate_task"] += 1
            return jax.vmap(lambda s, q, k, h: continual.evaluate_task(make(h, None), eval_config, s, q, i, k))(
                states, sequences, eval_keys, hparams)

        def heldout(states, tasks, keys, sequences, learnt, eval_keys, seed_index, hparams):
            self.traces["heldout"] += 1

            def fn(s, k, q, e, m, h):
                method = make(h, None)
                report = progress.with_fields(progress.host(self._receive), member=m)
                return (continual.heldout_adaptation(method, eval_config, s, tasks, k, report),
                        continual.learnt_tasks(method, eval_config, s, q, learnt, e))

            return jax.vmap(fn)(states, keys, sequences, eval_keys, seed_index, hparams)

        def init(rngs, hparams):
            self.traces["init"] += 1
            if not hparams:
                return continual.init_seeds(make({}, None), rngs)
            return continual.init_seeds(lambda h: make(h, None), rngs, hparams)

        shard = lambda f, specs: jax.jit(jax.shard_map(f, mesh=mesh, in_specs=specs, out_specs=seed,  # noqa: E731
                                                       check_vma=False))
        # Initialisation runs on one device (member by member, see continual.init_seeds), then is split over them.
        self._init = jax.jit(init)
        self._learn = shard(learn, (seed, seed, P(), seed, seed))
        self._evaluate_task = shard(evaluate_task, (seed, seed, P(), seed, seed))
        self._heldout = shard(heldout, (seed, P(), seed, seed, P(), seed, seed, seed))
        self.sharding = jax.sharding.NamedSharding(mesh, seed)

    def _receive(self, metrics: dict):
        if self.receiver is not None:
            self.receiver(metrics)

    def compile(self, part: str, *args, notify: Optional[Callable[[dict], None]] = None):
        """Compiles ``part`` (one of ``PARTS``) ahead of time for ``args`` (arrays or ``jax.ShapeDtypeStruct``s
        with their shardings) unless done; ``notify`` gets ``{"event": "compiling", "part"}`` before and
        ``{"event": "compiled", "part", "seconds", "trace_seconds"}`` after (from the persistent compile cache
        when it holds the program: then in about a second). Returns the ``jax.stages.Compiled``."""
        if part not in self.compiled:
            notify = notify or _silent
            notify({"event": "compiling", "part": part})
            start, hits = time.time(), compile_cache.hits()
            with _heartbeat(lambda: notify({"event": "compiling", "part": part, "seconds": time.time() - start})):
                traced = getattr(self, "_" + part).trace(*args)
                traced_at = time.time()
                self.compiled[part] = traced.lower().compile()
            notify({"event": "compiled", "part": part, "seconds": time.time() - start,
                    "trace_seconds": traced_at - start, "cached": compile_cache.hits() > hits})
        return self.compiled[part]

    def _call(self, part, *args):
        fn = self.compiled.get(part)
        return fn(*args) if fn is not None else getattr(self, "_" + part)(*args)

    def init(self, rngs, hparams: Optional[dict] = None):
        """The initial states of the members (keys ``rngs``), placed on the devices."""
        host = jax.device_put(jax.device_get((rngs, hparams or {})), jax.devices()[0])
        return self.put(jax.device_get(self._init(*host)))

    def learn(self, states, sequences, i, seed_index, hparams: Optional[dict] = None):
        """(states, TaskMetrics [members]) after learning the task at position ``i`` (i32[]) of ``sequences``."""
        return self._call("learn", states, sequences, i, seed_index, hparams or {})

    def evaluate_task(self, states, sequences, i, eval_keys, hparams: Optional[dict] = None):
        """``continual.TaskEvaluation`` [members] of ``states``, right after learning the task at position ``i``."""
        return self._call("evaluate_task", states, sequences, i, eval_keys, hparams or {})

    def run_chunk(self, states, sequences, start, eval_keys, seed_index, hparams: Optional[dict] = None):
        """(states, ChunkMetrics [members, chunk]): ``learn`` then ``evaluate_task`` for the ``chunk`` positions
        from ``start`` (an int); positions past the end of the sequence are not run and report zeros."""
        num_tasks = jax.tree.leaves(sequences)[0].shape[1]
        out = []
        for i in range(int(start), int(start) + self.chunk):
            if i >= num_tasks:
                out.append(jax.tree.map(jnp.zeros_like, out[-1]))
                continue
            states, metrics = self.learn(states, sequences, np.int32(i), seed_index, hparams)
            out.append(continual.chunk_metrics(metrics, self.evaluate_task(states, sequences, np.int32(i),
                                                                           eval_keys, hparams)))
        return states, jax.tree.map(lambda *x: jnp.stack(x, axis=1), *out)

    def heldout(self, states, tasks, keys, sequences, learnt, eval_keys, seed_index, hparams: Optional[dict] = None):
        """(HeldoutMetrics on ``tasks`` with ``keys``, Evaluation [members, num_tasks] of the ``learnt`` (i32[]) first
        tasks of ``sequences`` with ``eval_keys``, the backward-transfer keys)."""
        return self._call("heldout", states, tasks, keys, sequences, learnt, eval_keys, seed_index, hparams or {})

    def put(self, tree):
        """Places host arrays with a leading member axis on the devices, split along that axis."""
        return jax.device_put(tree, self.sharding)


class Programs:
    """Compiled method programs, kept per (method, family, config, traced fields, evaluation, chunk, devices), so
    that a resume or a second run through the same ``Programs`` does not compile again. Owned by its user (no
    module-level cache): ``run`` makes a fresh one unless given one; each program's progress goes to the run that
    is using it."""

    def __init__(self):
        self._programs: dict = {}

    def items(self):
        """(key, MethodProgram) pairs of the programs compiled so far."""
        return self._programs.items()

    def get(self, name, family_name, config, eval_config, chunk, devices, traced=()) -> MethodProgram:
        """The programs of method ``name`` with ``config``; the fields in ``traced`` (a grid's traced axes) are read
        per member from the programs' ``hparams`` argument instead of ``config``."""
        key = (name, family_name, config, tuple(traced), eval_config, chunk, devices)
        if key not in self._programs:
            family = envs.make(family_name)

            def make(hparams: dict, progress_fn) -> methods.Method:
                cfg = grids.with_traced(config, hparams) if hparams else config
                return methods.make(name, family, cfg, progress_fn=progress_fn)

            self._programs[key] = MethodProgram(make, eval_config, chunk, devices)
        return self._programs[key]


ProgressReceiver = Callable[[dict], None]
"""The runner's one callback to the outside world (brax's ``progress_fn``), called on the host with an event dict;
``event["event"]`` says which:

- ``start``: a program begins, before anything compiles (``program``, ``family``, ``sequence``, ``num_tasks``,
  ``seeds``, ``grid_points``, ``padding``, ``devices``, ``budget``, ``chunk``, ``start_task``: 0, ``members``:
  each member's name);
- ``compiling`` / ``compiled``: one of its programs (``PARTS``) is being compiled / is ready (``program``,
  ``family``, ``method``, ``part``, ``what``: its name in words; ``compiled`` adds ``seconds``,
  ``trace_seconds`` and ``cached``: whether it came from the persistent compile cache, ``jcomps.compile_cache``);
  a compile still running repeats ``compiling`` every ``HEARTBEAT_SECONDS`` with the ``seconds`` so far;
  ``learn`` compiles first and alone, the evaluation programs while the first task trains;
- ``resumed``: it continues from a checkpoint (``program``, ``step``, ``tasks_done``, ``num_tasks``);
- ``evaluating`` / ``evaluated``: the held-out meta-test and learnt-task evaluation after ``after_tasks`` tasks
  (0: the initial policies, measured after the first chunk) begins / ends (``seconds``); in between,
  ``heldout_iteration`` events give each member's adaptation progress (``member``, ``heldout_task``,
  ``heldout_iteration``, ``success_rate``, ``mean_return``);
- ``warning``: something was set aside (``message``), e.g. an unreadable checkpoint;
- ``iteration`` / ``meta_step``: a member's progress inside a chunk (``program``, ``member``, ``task`` and the
  ``jcomps.progress`` metrics: ``iteration``, ``success_rate``, ``mean_return`` / ``meta_step``,
  ``meta_steps``, ``bc_loss``, ``value_l2``, ``value_ev``, ``adv_abs``, ``rho``);
- ``compress_iteration``: the same for a compress phase of ``pnc`` (``compress_iteration``, ``compress_iterations``,
  ``kl``);
- ``chunk``: a chunk of tasks is done, per results entry (``program``, ``entry``, ``start``, ``stop``,
  ``num_tasks``, ``seeds``, ``metrics``: its members' ChunkMetrics, ``per_task``: every task's so far,
  ``learnt_tasks``: the Evaluation [members, num_tasks] of every task learnt, valid False where not evaluated),
  after the checkpoint is written;
- ``done``: the program finished (``program``, ``seconds``); ``skipped``: it had finished before (``program``).
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


def members(spec: grids.ProgramSpec, seeds: int, first_seed: int, devices: int) -> tuple[list, list, dict]:
    """The member layout of a program: (grid point index, seed) of every member, and the traced values
    ({field: f32[members]}). Point-major: member ``p * seeds + s`` is point ``p`` with seed ``first_seed + s``;
    padding members (up to a multiple of ``devices``) repeat point 0 with the next seeds, so without a grid the
    members are the seeds exactly as before grids existed."""
    real = len(spec.points) * seeds
    padded = padded_seeds(real, devices)
    point = [m // seeds for m in range(real)] + [0] * (padded - real)
    extra = first_seed + seeds
    seed = [first_seed + m % seeds for m in range(real)] + list(range(extra, extra + padded - real))
    hparams = {f: np.asarray([dict(spec.points[p].values)[f] for p in point], np.float32) for f in spec.traced}
    return point, seed, hparams


def run_program(out: str, spec: grids.ProgramSpec, run: RunConfig, eval_config: continual.EvalConfig, resume: bool,
                progress_fn: ProgressReceiver = _silent, programs: Optional[Programs] = None,
                stop_after_chunks: Optional[int] = None) -> Optional[dict]:
    """Runs (or resumes) one program (``jcomps.grid.programs``): its grid points × the seeds as one compiled
    chunk program; returns {entry key: RawResults} when the sequence is done. Events go to ``progress_fn``.

    Members are laid out by ``members``. A member uses its seed's keys and (stationary) task order, whatever its
    grid point. ``programs`` holds the compiled programs (default: a fresh cache). ``stop_after_chunks`` (tests)
    returns None after that many chunks of this call, as if killed.
    """
    family = envs.make(run.family)
    eval_config = eval_config.resolve(run.family)
    points = spec.points
    real = len(points) * run.seeds
    devices = num_devices(real)
    member_point, member_seed, hparams_host = members(spec, run.seeds, run.seed, devices)
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

    def notify(event: dict):
        """Compile events of this program, as the runner's ``compiling`` / ``compiled`` events."""
        progress_fn({**event, "program": name, "family": run.family, "method": spec.method,
                     "what": PART_NAMES[event["part"]]})

    member_names = [f"{points[p].key} seed {s}" for p, s in zip(member_point, member_seed)]
    progress_fn({"event": "start", "program": name, "family": run.family, "sequence": run.sequence,
                 "num_tasks": run.num_tasks, "seeds": run.seeds, "grid_points": len(points), "padding": padded - real,
                 "devices": devices, "budget": methods.collection(spec.config).budget_for(family),
                 "chunk": program.chunk, "start_task": 0, "members": member_names})
    init_keys = method_keys(member_seed)
    states = program.init(init_keys, hparams_host)
    # The learning program is the one a run waits for: it compiles first, alone.
    program.compile("learn", states, sequences, np.int32(0), seed_index, hparams, notify=notify)
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
        warn = lambda message: progress_fn({"event": "warning", "message": message})  # noqa: E731
        restored = checkpoints.restore_latest(record(states, per_task, heldout, 0, 0.0), warn)
        if restored is not None:
            step, tree = restored
            states = program.put(unflatten(states, tree["states"]))
            per_task = unflatten(per_task, tree["per_task"])
            heldout = unflatten(heldout, tree["heldout"])
            next_chunk, seconds = int(tree["counters"]["next_chunk"]), float(tree["counters"]["seconds"])
            progress_fn({"event": "resumed", "program": name, "step": step,
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
        program.compile("heldout", states, heldout_tasks, backward_keys, sequences, np.int32(0), backward_keys,
                        seed_index, hparams, notify=notify)

    def evaluate(states, column: int, learnt: int, keys, after: int):
        """The evaluations of ``states`` (``learnt``: the tasks to evaluate) into column ``column`` of ``heldout``
        (``after``: the tasks learnt, for the progress lines)."""
        compile_heldout(states)
        progress_fn({"event": "evaluating", "program": name, "after_tasks": after, "learnt": learnt})
        began = time.time()
        out_h = jax.device_get(program.heldout(states, heldout_tasks, program.put(keys), sequences, np.int32(learnt),
                                               backward_keys, seed_index, hparams))
        jax.tree.map(lambda dst, src: dst.__setitem__((slice(None), column), np.asarray(src)), heldout, out_h)
        progress_fn({"event": "evaluated", "program": name, "after_tasks": after, "seconds": time.time() - began})
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
                program.compile("evaluate_task", states, sequences, np.int32(i), backward_keys, hparams,
                                notify=notify)
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
                progress_fn({"event": "chunk", "program": name, "entry": point.key, "start": start, "stop": stop,
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
    progress_fn({"event": "done", "program": name, "seconds": total})
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
                progress_fn({"event": "skipped", "program": spec.label})
            else:
                done = run_program(out, spec, run_config, eval_config, resume, progress_fn, programs)
            raws.update(done)
    return raws
