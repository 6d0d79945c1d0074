"""Experiment runs: methods over a task sequence, seeds sharded over devices, chunked, checkpointed, resumable.

A run directory holds:

- ``run.json``: everything that defines the run (run options, evaluation options, every method's config, the
  hyperparameter grid if any); a resume must match it.
- ``checkpoints/<program>/<step>/``: Orbax checkpoints of a program's entire state (parameters, optimiser
  states, experience stores, rng, counters) and the metrics so far, written after every chunk of tasks. A
  program is a method (``checkpoints/<method>``), or with a grid one per combination of its shape-changing
  values (``checkpoints/<method>@hidden_sizes=64x32``).
- ``raw/<entry>.npz``: all metrics of a results entry (a method, or a method at a grid point) once its program
  is done (the input of ``jcomps.report``).
- ``results.json``, ``plots/*.png``, ``significance.md``: written by ``jcomps.report`` at the end.

Per program there is one compiled chunk program: ``vmap`` over the members of a device, ``shard_map`` over
devices (the member axis), a ``lax.scan`` over ``chunk_tasks`` tasks. Members are the seeds, or with a grid
(``jcomps.grid``) the program's grid points × the seeds, point-major; traced hyperparameters enter as one
scalar per member, and the method is made inside the traced function from a config holding it. The host loops
over chunks and checkpoints between them; since every chunk runs through the same program from the restored
state, a resumed run gives per-task results identical to an uninterrupted one.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import time
from typing import Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import PartitionSpec as P

from jcomps import continual, envs, grid as grids, methods
from jcomps.ppo import check_field


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


class RunError(ValueError):
    """A run directory or its options cannot be used as asked (the runner turns it into exit code 2)."""


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


def _write_json(path, data):
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(data, f, indent=1)
    os.replace(tmp, path)


def open_run_dir(out: str, description: dict, resume: bool) -> None:
    """Creates ``out`` for a new run, or checks that it holds this very run when resuming."""
    run_json = os.path.join(out, "run.json")
    if resume:
        if not os.path.isfile(run_json):
            raise RunError(f"--resume: {out} holds no run (no run.json); start it without --resume")
        with open(run_json) as f:
            stored = json.load(f)
        diff = _differences(stored, description)
        diff = [d + f" (float rounding depends on it: resume with --devices {stored['devices']})"
                if d.startswith("devices:") else d for d in diff]
        if diff:
            raise RunError(f"--resume: {out} was made with another config: " + "; ".join(diff[:8]))
        return
    if os.path.exists(run_json) or os.path.exists(os.path.join(out, "results.json")):
        raise RunError(f"{out} already holds a run; choose another --out, or add --resume to continue it")
    os.makedirs(out, exist_ok=True)
    _write_json(run_json, description)


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


def method_keys(seeds: list[int]) -> jax.Array:
    """Each seed's key for ``method.init`` (everything the method draws descends from it)."""
    return jax.vmap(lambda s: jax.random.fold_in(jax.random.PRNGKey(s), METHOD_SALT))(jnp.asarray(seeds, jnp.uint32))


def eval_keys(seeds: list[int], purpose: int) -> jax.Array:
    """Each seed's key for the evaluation ``purpose`` (1: backward transfer; 1000 + c: held-out after chunk c)."""
    return jax.vmap(lambda s: jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(s), EVAL_SALT), purpose))(
        jnp.asarray(seeds, jnp.uint32))


class Progress:
    """Host-side progress of one program: a status line at most every ``interval`` seconds, from the callbacks
    of every RL iteration (program, task, iteration, success rate, elapsed, remaining) and of every outer update
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
        self.meta_loss = np.full(seeds, np.nan)

    def __call__(self, context, iteration, success_rate, mean_return):
        del mean_return
        seed, task = (int(x) for x in context)
        self.task[seed], self.iteration[seed], self.success[seed] = task, int(iteration), float(success_rate)
        self._throttled(self.line)

    def meta_step(self, context, step, steps, loss):
        """After every outer update of a meta-training phase (between two tasks)."""
        seed, task = (int(x) for x in context)
        self.meta_loss[seed] = float(loss)
        self._throttled(lambda: f"[{self.name}] task {task + 1}/{self.num_tasks} meta-training step {int(step)}/"
                                f"{int(steps)} bc loss {float(np.nanmean(self.meta_loss)):.3f}{self._behind()} | "
                                f"elapsed {_clock(time.time() - self.start)} remaining {self._remaining_text()}")

    def _throttled(self, line: Callable[[], str]):
        now = time.time()
        if now - self.last >= self.interval:
            self.last = now
            self.log(line())

    def _remaining_text(self) -> str:
        remaining = self.remaining()
        return "?" if remaining is None else "~" + _clock(remaining)

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
        return (f"[{self.name}] task {tasks}/{self.num_tasks} iteration {int(self.iteration.max())} success "
                f"{float(self.success.mean()):.2f}{self._behind()} | elapsed {_clock(time.time() - self.start)} "
                f"remaining {self._remaining_text()}")


def _clock(seconds: float) -> str:
    seconds = int(seconds)
    return f"{seconds // 3600}h{seconds // 60 % 60:02d}m" if seconds >= 3600 else f"{seconds // 60}m{seconds % 60:02d}s"


class MethodProgram:
    """The compiled programs of one method: init, one chunk of tasks, held-out adaptation; members sharded.

    ``make(hparams)`` makes the method from one member's dict of traced hyperparameters (empty without traced
    grid axes); it runs inside each traced function, so every member learns, is initialised and is evaluated
    with its own values. Every program takes ``hparams``, a dict of f32[members] arrays (default: none).
    ``traces`` counts how often each program was traced (once each, however many chunks run).
    """

    def __init__(self, make: Callable[[dict], methods.Method], eval_config: continual.EvalConfig, chunk: int,
                 devices: int):
        self.make, self.chunk = make, chunk
        self.traces: dict = {"init": 0, "run_chunk": 0, "heldout": 0}
        mesh = jax.make_mesh((devices,), ("seed",), devices=jax.devices()[:devices])
        seed = P("seed")

        def run_chunk(states, sequences, start, eval_keys, seed_index, hparams):
            self.traces["run_chunk"] += 1
            fn = lambda s, q, k, i, h: continual.run_chunk(make(h), eval_config, s, q, start, chunk, k, i)  # noqa: E731
            return jax.vmap(fn)(states, sequences, eval_keys, seed_index, hparams)

        def heldout(states, tasks, keys, hparams):
            self.traces["heldout"] += 1
            return jax.vmap(lambda s, k, h: continual.heldout_adaptation(make(h), eval_config, s, tasks, k))(
                states, keys, hparams)

        def init(rngs, hparams):
            self.traces["init"] += 1
            if not hparams:
                return continual.init_seeds(make({}), rngs)
            return continual.init_seeds(make, rngs, hparams)

        shard = lambda f, specs: jax.jit(jax.shard_map(f, mesh=mesh, in_specs=specs, out_specs=seed,  # noqa: E731
                                                       check_vma=False))
        # Initialisation runs on one device (member by member, see continual.init_seeds), then is split over them.
        self._init = jax.jit(init)
        self._run_chunk = shard(run_chunk, (seed, seed, P(), seed, seed, seed))
        self._heldout = shard(heldout, (seed, P(), seed, seed))
        self.sharding = jax.sharding.NamedSharding(mesh, seed)

    def init(self, rngs, hparams: Optional[dict] = None):
        """The initial states of the members (keys ``rngs``), placed on the devices."""
        host = jax.device_put(jax.device_get((rngs, hparams or {})), jax.devices()[0])
        return self.put(jax.device_get(self._init(*host)))

    def run_chunk(self, states, sequences, start, eval_keys, seed_index, hparams: Optional[dict] = None):
        return self._run_chunk(states, sequences, start, eval_keys, seed_index, hparams or {})

    def heldout(self, states, tasks, keys, hparams: Optional[dict] = None):
        return self._heldout(states, tasks, keys, hparams or {})

    def put(self, tree):
        """Places host arrays with a leading member axis on the devices, split along that axis."""
        return jax.device_put(tree, self.sharding)


class _Hooks:
    """The progress hooks compiled into a program; ``progress`` is the current run's ``Progress`` (or None)."""

    def __init__(self):
        self.progress: Optional[Progress] = None

    def on_iteration(self, context, iteration, success_rate, mean_return):
        if self.progress is not None:
            self.progress(context, iteration, success_rate, mean_return)

    def on_meta_step(self, context, step, steps, loss):
        if self.progress is not None:
            self.progress.meta_step(context, step, steps, loss)


# Compiled programs are kept per (method, family, config, traced fields, evaluation, chunk, devices), so a resume
# or a second run in the same process does not compile again; progress reaches the current run's Progress
# through the program's hooks.
_PROGRAMS: dict = {}


def _program(name, family_name, config, eval_config, chunk, devices, traced=()) -> MethodProgram:
    """The programs of method ``name`` with ``config``; the fields in ``traced`` (a grid's traced axes) are read
    per member from the programs' ``hparams`` argument instead of ``config``."""
    key = (name, family_name, config, tuple(traced), eval_config, chunk, devices)
    if key not in _PROGRAMS:
        hooks = _Hooks()
        family = envs.make(family_name)

        def make(hparams: dict) -> methods.Method:
            cfg = grids.with_traced(config, hparams) if hparams else config
            return methods.make(name, family, cfg, on_iteration=hooks.on_iteration, on_meta_step=hooks.on_meta_step)

        program = MethodProgram(make, eval_config, chunk, devices)
        program.hooks = hooks
        _PROGRAMS[key] = program
    return _PROGRAMS[key]


def _flatten(tree) -> dict:
    """The leaves of ``tree`` by index; empty arrays (e.g. backward transfer with ``--backward-tasks 0``) hold
    nothing and are left out, since Orbax refuses to save zero-size arrays."""
    return {f"{i:05d}": np.asarray(x) for i, x in enumerate(jax.tree.leaves(tree)) if np.size(x) > 0}


def _unflatten(like, flat: dict):
    """The inverse of ``_flatten`` (``flat`` checked against ``like`` by ``Checkpoints.restore_latest``)."""
    leaves, treedef = jax.tree.flatten(like)
    return jax.tree.unflatten(treedef, [flat[f"{i:05d}"] if np.size(x) > 0 else np.zeros(np.shape(x), x.dtype)
                                        for i, x in enumerate(leaves)])


def _record(states, per_task, heldout, next_chunk: int, seconds: float) -> dict:
    """What a checkpoint holds: flat arrays of the states and the metrics so far, and the counters."""
    return {"states": _flatten(states), "per_task": _flatten(per_task), "heldout": _flatten(heldout),
            "counters": {"next_chunk": np.int64(next_chunk), "seconds": np.float64(seconds)}}


class Checkpoints:
    """Orbax checkpoints of one method (atomic: Orbax writes to a temporary directory and renames)."""

    def __init__(self, directory: str):
        import orbax.checkpoint as ocp
        self.ocp = ocp
        self.directory = os.path.abspath(directory)
        self._open()

    def _open(self):
        self.manager = self.ocp.CheckpointManager(
            self.directory,
            options=self.ocp.CheckpointManagerOptions(max_to_keep=2, create=True, enable_async_checkpointing=False))

    def _set_aside(self, step: int) -> str:
        """Moves an unreadable step out of the way (kept for inspection, never deleted)."""
        dest = os.path.join(self.directory + "-unreadable", f"{step}-{time.strftime('%Y%m%d-%H%M%S')}")
        os.makedirs(os.path.dirname(dest), exist_ok=True)
        shutil.move(os.path.join(self.directory, str(step)), dest)
        return dest

    def save(self, step: int, tree: dict):
        self.manager.save(step, args=self.ocp.args.StandardSave(tree), force=True)
        self.manager.wait_until_finished()

    def restore_latest(self, like: dict, log) -> Optional[tuple[int, dict]]:
        """The newest readable checkpoint (an unreadable one is reported and the one before it is tried)."""
        errors = []
        for step in sorted(self.manager.all_steps(), reverse=True):
            try:
                target = jax.tree.map(np.asarray, like)
                tree = self.manager.restore(step, args=self.ocp.args.StandardRestore(target))
                tree = jax.tree.map(np.asarray, tree)
                _check_like(target, tree)
                if errors:
                    self._open()
                return step, tree
            except Exception as err:  # noqa: BLE001 - any failure to read means this checkpoint is unusable
                errors.append(f"step {step}: {type(err).__name__}: {str(err)[:300]}")
                dest = self._set_aside(step)
                log(f"warning: checkpoint step {step} in {self.directory} cannot be read ({errors[-1]}); moved to "
                    f"{dest}")
        if errors:
            raise RunError("no readable checkpoint (unreadable ones were moved to "
                           f"{self.directory}-unreadable): " + " | ".join(errors))
        return None


def _check_like(like: dict, got: dict):
    """Raises RunError unless ``got`` has the structure, shapes and dtypes of ``like``."""
    if jax.tree.structure(like) != jax.tree.structure(got):
        raise RunError("checkpoint entries differ from this method's state")
    for path, a in jax.tree_util.tree_leaves_with_path(like):
        b = got
        for key in path:
            b = b[key.key]
        if a.shape != b.shape or a.dtype != b.dtype:
            raise RunError(f"checkpoint entry {jax.tree_util.keystr(path)} is {b.dtype}{list(b.shape)}, expected "
                           f"{a.dtype}{list(a.shape)}")


def run_method(out: str, name: str, run: RunConfig, eval_config: continual.EvalConfig, config, resume: bool,
               log: Callable[[str], None] = print, tensorboard: bool = False,
               stop_after_chunks: Optional[int] = None) -> Optional[dict]:
    """Runs (or resumes) one method's sequence, without a grid; returns its raw metrics (numpy) when the sequence
    is done.

    ``stop_after_chunks`` (tests) returns None after that many chunks of this call, as if killed.
    """
    spec, = grids.programs(name, config, ())
    raws = run_program(out, spec, run, eval_config, resume, log, tensorboard, stop_after_chunks)
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
                log: Callable[[str], None] = print, tensorboard: bool = False,
                stop_after_chunks: Optional[int] = None) -> Optional[dict]:
    """Runs (or resumes) one program (``jcomps.grid.programs``): its grid points × the seeds as one compiled
    chunk program; returns {entry key: raw metrics (numpy)} when the sequence is done.

    Members are laid out by ``members``. A member uses its seed's keys and (stationary) task order, whatever its
    grid point. ``stop_after_chunks`` (tests) returns None after that many chunks of this call, as if killed.
    """
    family = envs.make(run.family)
    points = spec.points
    real = len(points) * run.seeds
    devices = num_devices(real)
    member_point, member_seed, hparams_host = members(spec, run.seeds, run.seed, devices)
    padded = len(member_seed)
    program = _program(spec.method, run.family, spec.config, eval_config, min(run.chunk_tasks, run.num_tasks),
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

    states = program.init(method_keys(member_seed), hparams_host)
    chunk_shapes = jax.eval_shape(program.run_chunk, states, sequences, jnp.int32(0), backward_keys, seed_index,
                                  hparams)[1]
    heldout_shapes = jax.eval_shape(program.heldout, states, heldout_tasks, backward_keys, hparams)
    # Host copies of every metric of the sequence, filled chunk by chunk: [members, num_tasks, ...].
    per_task = jax.tree.map(lambda x: np.zeros((x.shape[0], run.num_tasks) + x.shape[2:], x.dtype), chunk_shapes)
    heldout = jax.tree.map(lambda x: np.zeros((x.shape[0], num_chunks + 1) + x.shape[1:], x.dtype), heldout_shapes)

    checkpoints = Checkpoints(os.path.join(out, "checkpoints", spec.directory))
    next_chunk, seconds = 0, 0.0
    if resume:
        restored = checkpoints.restore_latest(_record(states, per_task, heldout, 0, 0.0), log)
        if restored is not None:
            step, tree = restored
            states = program.put(_unflatten(states, tree["states"]))
            per_task = _unflatten(per_task, tree["per_task"])
            heldout = _unflatten(heldout, tree["heldout"])
            next_chunk, seconds = int(tree["counters"]["next_chunk"]), float(tree["counters"]["seconds"])
            log(f"[{name}] resumed from checkpoint {step}: {min(next_chunk * program.chunk, run.num_tasks)}/"
                f"{run.num_tasks} tasks done")
    writers = [_tensorboard(out, p.key) for p in points] if tensorboard else None

    extra = f" (+{padded - real} to fill the devices, not reported)" if padded > real else ""
    grid_text = f" × {len(points)} grid points = {real} members" if len(points) > 1 else ""
    log(f"[{name}] {run.family} {run.sequence}, {run.num_tasks} tasks, {run.seeds} seeds{grid_text}{extra} on "
        f"{devices} device(s), budget {spec.config.ppo.budget_for(family)}, chunks of {program.chunk}; compiling...")
    start_time = time.time()
    if next_chunk == 0:
        out_h = program.heldout(states, heldout_tasks, program.put(eval_keys(member_seed, 1000)), hparams)
        jax.tree.map(lambda dst, src: dst.__setitem__((slice(None), 0), np.asarray(src)), heldout, out_h)
    member_names = [f"{points[p].key} seed {s}" for p, s in zip(member_point, member_seed)]
    program.hooks.progress = Progress(name, padded, run.num_tasks, next_chunk * program.chunk, log,
                                      members=member_names if len(points) > 1 else None)
    # The reported members of each point (padding members are dropped).
    slices = [(slice(p * run.seeds, (p + 1) * run.seeds),) for p in range(len(points))]
    seeds = list(range(run.seed, run.seed + run.seeds))
    chunks_run = 0
    for c in range(next_chunk, num_chunks):
        start = c * program.chunk
        states, metrics = program.run_chunk(states, sequences, jnp.int32(start), backward_keys, seed_index, hparams)
        metrics = jax.device_get(metrics)
        stop = min(start + program.chunk, run.num_tasks)
        jax.tree.map(lambda dst, src: dst.__setitem__((slice(None), slice(start, stop)), src[:, :stop - start]),
                     per_task, metrics)
        out_h = program.heldout(states, heldout_tasks, program.put(eval_keys(member_seed, 1001 + c)), hparams)
        jax.tree.map(lambda dst, src: dst.__setitem__((slice(None), c + 1), np.asarray(src)), heldout, out_h)
        for p, point in enumerate(points):
            reported = jax.tree.map(lambda x: x[slices[p]], metrics)
            _report_chunk(log, point.key, reported, start, stop, run.num_tasks)
            _check_finite(log, point.key, seeds, reported.task.per_iteration.nonfinite, start)
            if writers is not None:
                _log_tensorboard(writers[p], jax.tree.map(lambda x: x[slices[p]], per_task), start, stop)
        elapsed = seconds + time.time() - start_time
        checkpoints.save(c + 1, _record(states, per_task, heldout, c + 1, elapsed))
        chunks_run += 1
        if stop_after_chunks is not None and chunks_run >= stop_after_chunks and c + 1 < num_chunks:
            program.hooks.progress = None
            return None
    program.hooks.progress = None
    total = seconds + time.time() - start_time
    raws = {}
    for p, point in enumerate(points):
        raws[point.key] = {"per_task": jax.tree.map(lambda x: x[slices[p]], per_task),
                           "heldout": jax.tree.map(lambda x: x[slices[p]], heldout), "seconds": total,
                           "devices": devices, "heldout_after_tasks": [min(c * program.chunk, run.num_tasks)
                                                                       for c in range(num_chunks + 1)]}
        save_raw(out, point.key, raws[point.key])
    log(f"[{name}] done in {_clock(total)}")
    return raws


def _report_chunk(log, name, metrics, start, stop, num_tasks):
    its = np.asarray(metrics.task.iterations)[:, :stop - start]
    for t in range(stop - start):
        log(f"[{name}] task {start + t + 1}/{num_tasks} iterations-to-success per seed: {its[:, t].tolist()} "
            f"(mean {its[:, t].mean():.1f})")


def _check_finite(log, name, seeds, nonfinite, start):
    bad = np.argwhere(np.asarray(nonfinite) > 0)
    if len(bad):
        s, t, it = bad[0]
        log(f"error: [{name}] non-finite values (NaN/inf) at seed {seeds[s]}, task {start + t + 1}, iteration "
            f"{it + 1}; those updates were skipped, not trained on")


def _tensorboard(out, name):
    try:
        from tensorboardX import SummaryWriter
    except ImportError as err:
        raise RunError("--tensorboard needs tensorboardX: pip install -e '.[tensorboard]'") from err
    return SummaryWriter(os.path.join(out, "tensorboard", name))


def _log_tensorboard(writer, per_task, start, stop):
    task = per_task.task
    its = np.asarray(task.iterations)
    for t in range(start, stop):
        writer.add_scalar("iterations_to_success/mean", float(its[:, t].mean()), t + 1)
        for s in range(its.shape[0]):
            writer.add_scalar(f"iterations_to_success/seed{s}", float(its[s, t]), t + 1)
            valid = np.asarray(task.per_iteration.valid[s, t])
            offset = int(np.sum(np.asarray(task.per_iteration.valid[s, :t])))
            for i in np.flatnonzero(valid):
                writer.add_scalar(f"lifelong_return/seed{s}", float(task.per_iteration.mean_return[s, t, i]),
                                  offset + i + 1)
                writer.add_scalar(f"lifelong_success/seed{s}", float(task.per_iteration.success_rate[s, t, i]),
                                  offset + i + 1)
    writer.flush()


def save_raw(out: str, name: str, raw: dict) -> None:
    """Writes a finished results entry's metrics (a method, or a method at a grid point) to ``raw/<name>.npz``
    atomically."""
    os.makedirs(os.path.join(out, "raw"), exist_ok=True)
    arrays = {"seconds": np.float64(raw["seconds"]), "devices": np.int64(raw["devices"]),
              "heldout_after_tasks": np.asarray(raw["heldout_after_tasks"], np.int64)}
    per_task = raw["per_task"]
    arrays.update({f"task.{k}": np.asarray(v) for k, v in per_task.task._asdict().items() if k != "per_iteration"})
    arrays.update({f"iter.{k}": np.asarray(v) for k, v in per_task.task.per_iteration._asdict().items()})
    arrays.update({"backward_returns": per_task.backward_returns, "backward_valid": per_task.backward_valid})
    arrays.update({"heldout_return": raw["heldout"][0], "heldout_success": raw["heldout"][1]})
    path = os.path.join(out, "raw", f"{name}.npz")
    with open(path + ".tmp", "wb") as f:
        np.savez(f, **arrays)
    os.replace(path + ".tmp", path)


def load_raw(out: str, name: str) -> Optional[dict]:
    """A finished results entry's metrics, or None if it has not finished."""
    path = os.path.join(out, "raw", f"{name}.npz")
    if not os.path.isfile(path):
        return None
    try:
        with np.load(path) as f:
            return {k: f[k] for k in f.files}
    except Exception as err:  # noqa: BLE001
        raise RunError(f"{path} cannot be read ({type(err).__name__}: {err}); delete it to rerun {name}") from err


def run(out: str, run_config: RunConfig, eval_config: continual.EvalConfig, method_configs: dict,
        resume: bool = False, log: Callable[[str], None] = print, tensorboard: bool = False,
        grid: grids.Grid = (), overrides: Optional[dict] = None) -> dict:
    """Runs every method of ``run_config`` into ``out`` (resuming where it stopped), each at every point of the
    hyperparameter ``grid`` (``jcomps.grid``; empty: no grid); returns raw metrics by results entry key."""
    open_run_dir(out, describe(run_config, eval_config, method_configs, grid, overrides), resume)
    raws = {}
    for name in run_config.methods:
        for spec in grids.programs(name, method_configs[name], grid):
            done = {p.key: load_raw(out, p.key) for p in spec.points} if resume else {}
            if done and all(raw is not None for raw in done.values()):
                log(f"[{spec.label}] already finished; skipping")
            else:
                run_program(out, spec, run_config, eval_config, resume, log, tensorboard)
                done = {p.key: load_raw(out, p.key) for p in spec.points}
            raws.update(done)
    return raws
