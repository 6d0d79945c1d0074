"""The compiled programs of a method, and their cache.

Per method there are four programs (``PARTS``): ``init``, ``learn`` (one task at a position of the sequence; the
host loops over positions, so one program serves every task), ``evaluate_task`` (backward transfer and the learnt
task, after each task) and ``measure`` (held-out meta-test and the learnt tasks, after each chunk). Each is a
``vmap`` over the members of a device and a ``shard_map`` over devices (``jcomps.runner.members``: the member axis);
traced hyperparameters enter as one scalar per member, and the method is made inside the traced function from a
config holding it. Programs compile ahead of time (``MethodProgram.compile``, timed, with a heartbeat while XLA
works) and live in a ``Programs`` cache owned by the caller, never in a module-level registry.
"""

from __future__ import annotations

import contextlib
import inspect
import threading
import time
from typing import Any, Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import PartitionSpec as P

from jcomps import continual, envs, methods, progress
from jcomps.runner import compile_cache, distributed
from jcomps.runner import grid as grids

HEARTBEAT_SECONDS = 20.0
"""How often a compile that is still running says so (``MethodProgram.compile``'s ``waiting``)."""


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


PARTS = ("init", "learn", "evaluate_task", "measure")
"""The compiled programs of a method (``MethodProgram``), in the order a run first needs them."""

PART_NAMES = {"init": "init", "learn": "learning", "evaluate_task": "per-task evaluation",
              "measure": "held-out meta-test and learnt-task evaluation"}
"""What each program is called in progress lines."""


class CompileTimes(NamedTuple):
    """How long ``MethodProgram.compile`` took for one program."""

    seconds: float
    """From the start of tracing until the program was ready."""
    trace_seconds: float
    """Of which Python tracing (never cached)."""
    cached: bool
    """Whether XLA's part came from the persistent compile cache (``jcomps.runner.compile_cache``): then in about a
    second."""


class MethodProgram:
    """The compiled programs of one method, members sharded over the devices (``PARTS``):

    - ``init``: the members' initial states;
    - ``learn``: learns the task at one position of the sequence (``continual.learn_at``); the host loops over
      positions, one program for every task;
    - ``evaluate_task``: the evaluations right after a task is learnt (backward transfer, the learnt task itself:
      ``continual.evaluate_task``);
    - ``measure``: after a chunk of tasks, the held-out adaptation and the learnt tasks' evaluation
      (``continual.Measurement``: ``heldout_adaptation``, ``learnt_tasks``).

    Each holds the simulator once at most, so that the program on the critical path (``learn``) compiles alone and
    the evaluation programs can compile while the first task trains (``compile``: ahead of time, timed).

    ``make(hparams, progress_fn)`` makes the method from one member's dict of traced hyperparameters (empty
    without traced grid axes) and progress hook; it runs inside each traced function, so every member learns, is
    initialised and is evaluated with its own values. Every program takes ``hparams``, a dict of f32[members]
    arrays (empty: none). A run calls them through ``bind`` (a ``BoundProgram`` holding its inputs). ``traces``
    says how often each program was traced (once each, however many tasks run). While a program runs, every member's progress metrics (``jcomps.progress``) reach ``receiver`` (a host
    function of one dict, set by whoever runs the program; None: dropped) with the member's index as ``member``.
    """

    def __init__(self, make: Callable[..., methods.Method], eval_config: continual.EvalConfig, chunk: int,
                 devices: int):
        self.make, self.chunk, self.eval_config = make, chunk, eval_config
        self.receiver: Optional[Callable[[dict], None]] = None
        self.compiled: dict = {}
        """Part -> its ``jax.stages.Compiled``, once ``compile`` made it."""
        mesh = jax.make_mesh((devices,), ("seed",), devices=jax.devices()[:devices])
        seed = P("seed")

        def learn(states, sequences, i, seed_index, hparams):
            def fn(s, q, m, h):
                # The hook closes over the member's (traced) index: the method reports its task, we add who it is.
                report = progress.host(self._receive)
                return continual.learn_at(make(h, progress.with_fields(report, member=m)), s, q, i)

            return jax.vmap(fn)(states, sequences, seed_index, hparams)

        def evaluate_task(states, sequences, i, eval_keys, hparams):
            return jax.vmap(lambda s, q, k, h: continual.evaluate_task(make(h, None), eval_config, s, q, i, k))(
                states, sequences, eval_keys, hparams)

        def measure(states, tasks, keys, sequences, learnt, eval_keys, seed_index, hparams):
            def fn(s, k, q, e, m, h):
                method = make(h, None)
                report = progress.with_fields(progress.host(self._receive), member=m)
                return continual.Measurement(continual.heldout_adaptation(method, eval_config, s, tasks, k, report),
                                             continual.learnt_tasks(method, eval_config, s, q, learnt, e))

            return jax.vmap(fn)(states, keys, sequences, eval_keys, seed_index, hparams)

        def init(rngs, hparams):
            if not hparams:
                return continual.init_seeds(make({}, None), rngs)
            return continual.init_seeds(lambda h: make(h, None), rngs, hparams)

        def shard(f, shared: frozenset):
            """``f`` jitted with its arguments split over the devices along the members' axis, but for those
            named in ``shared`` (the same on every device), and its outputs split the same way."""
            specs = tuple(P() if name in shared else seed for name in inspect.signature(f).parameters)
            return jax.jit(jax.shard_map(f, mesh=mesh, in_specs=specs, out_specs=seed, check_vma=False))

        # Initialisation runs on one device (member by member, see continual.init_seeds), then is split over them.
        self._init = jax.jit(init)
        self._learn = shard(learn, shared=frozenset({"i"}))
        self._evaluate_task = shard(evaluate_task, shared=frozenset({"i"}))
        self._measure = shard(measure, shared=frozenset({"tasks", "learnt"}))
        self.sharding = jax.sharding.NamedSharding(mesh, seed)

    @property
    def traces(self) -> dict:
        """Part -> how often it was traced and compiled: ahead of time by ``compile`` (once at most) and by
        ``jax.jit`` when a part is called without it (one entry of the jitted function's cache per signature it
        met). Read from the host, nothing counted inside the traced functions."""
        return {part: int(part in self.compiled) + getattr(self, "_" + part)._cache_size() for part in PARTS}

    def _receive(self, metrics: dict):
        if self.receiver is not None:
            self.receiver(metrics)

    def compile(self, part: str, *args, waiting: Optional[Callable[[float], None]] = None
                ) -> Optional[CompileTimes]:
        """Compiles ``part`` (one of ``PARTS``) ahead of time for ``args`` (arrays or ``jax.ShapeDtypeStruct``s
        with their shardings) unless done; while it compiles, ``waiting`` gets the seconds so far every
        ``HEARTBEAT_SECONDS``. Returns how long it took, or None when it was compiled before (the
        ``jax.stages.Compiled`` is then in ``compiled[part]``)."""
        if part in self.compiled:
            return None
        start, hits = time.time(), compile_cache.hits()
        beat = (lambda: None) if waiting is None else (lambda: waiting(time.time() - start))
        with _heartbeat(beat):
            traced = getattr(self, "_" + part).trace(*args)
            traced_at = time.time()
            self.compiled[part] = traced.lower().compile()
        return CompileTimes(time.time() - start, traced_at - start, compile_cache.hits() > hits)

    def init(self, rngs, hparams: Optional[dict] = None):
        """The initial states of the members (keys ``rngs``), placed on the devices."""
        # Every process computes every member's state on its first device and keeps its own members' part.
        host = jax.device_put(jax.device_get((rngs, hparams or {})), jax.local_devices()[0])
        return self.put(jax.device_get(self._init(*host)))

    def bind(self, sequences, seed_index, eval_keys, hparams: Optional[dict], heldout_tasks) -> "BoundProgram":
        """These programs with one run's inputs (host arrays, placed on the devices once: ``ProgramInput``)."""
        return BoundProgram(self, ProgramInput(self.put(sequences), self.put(seed_index), self.put(eval_keys),
                                               self.put(hparams or {}), heldout_tasks))

    def put(self, tree):
        """Places host arrays with a leading member axis on the devices, split along that axis (with several
        processes, each process its own members: ``jcomps.runner.distributed.put``)."""
        return distributed.put(tree, self.sharding)


class ProgramInput(NamedTuple):
    """What every call of one run's programs shares, built once (``MethodProgram.bind``) and kept by its
    ``BoundProgram``; all but ``heldout_tasks`` split over the devices along the members' axis."""

    sequences: Any
    """The members' task sequences: the family's task pytree [members, num_tasks, ...]."""
    seed_index: Any
    """i32[members]: each member's index (its progress events' ``member``)."""
    eval_keys: Any
    """[members, ...] keys of the evaluations of the learnt tasks (backward transfer, ``learnt_tasks``)."""
    hparams: dict
    """{field: f32[members]} of the traced hyperparameters (empty without traced grid axes)."""
    heldout_tasks: Any
    """The family's held-out tasks (host arrays, the same on every device)."""


class BoundProgram:
    """A method's compiled programs (``MethodProgram``) with one run's inputs (``ProgramInput``): the calls a run
    makes take only what changes from call to call (the states, a task position, the held-out keys)."""

    def __init__(self, program: MethodProgram, inputs: ProgramInput):
        self.program, self.inputs = program, inputs

    def arguments(self, part: str, states, i=0, keys=None, learnt=0) -> tuple:
        """The arguments of ``part``'s compiled function (``MethodProgram.compile`` compiles for them)."""
        x, i, learnt = self.inputs, np.int32(i), np.int32(learnt)
        if part == "learn":
            return states, x.sequences, i, x.seed_index, x.hparams
        if part == "evaluate_task":
            return states, x.sequences, i, x.eval_keys, x.hparams
        if part == "measure":
            keys = x.eval_keys if keys is None else keys  # the held-out keys are shaped as the learnt tasks'
            return states, x.heldout_tasks, keys, x.sequences, learnt, x.eval_keys, x.seed_index, x.hparams
        raise ValueError(f"part must be one of learn, evaluate_task, measure, got {part!r}")

    def _call(self, part: str, *args):
        fn = self.program.compiled.get(part)
        return fn(*args) if fn is not None else getattr(self.program, "_" + part)(*args)

    def learn(self, states, i: int):
        """(states, TaskMetrics [members]) after learning the task at position ``i`` of the sequences."""
        return self._call("learn", *self.arguments("learn", states, i))

    def evaluate_task(self, states, i: int):
        """``continual.TaskEvaluation`` [members] of ``states``, right after learning the task at position ``i``."""
        return self._call("evaluate_task", *self.arguments("evaluate_task", states, i))

    def learn_chunk(self, states, start: int, stop: int, after_learn: Optional[Callable] = None):
        """(states, ChunkMetrics [members, stop - start]) after learning the tasks at positions ``start`` ..
        ``stop - 1`` in turn, each evaluated right after it is learnt (``learn``, then ``evaluate_task``): the
        runner's chunk of tasks, the one way a chunk runs. ``after_learn(states)`` is called after each ``learn`` is
        dispatched, before its evaluation (the runner compiles the evaluation programs there, while the first task
        trains)."""
        task_metrics = []
        for i in range(start, stop):
            states, learnt = self.learn(states, i)
            if after_learn is not None:
                after_learn(states)
            task_metrics.append(continual.chunk_metrics(learnt, self.evaluate_task(states, i)))
        return states, jax.tree.map(lambda *x: jnp.stack(x, axis=1), *task_metrics)

    def measure(self, states, keys, learnt: int):
        """``continual.Measurement`` [members]: HeldoutMetrics on the held-out tasks with ``keys`` (host keys
        [members, ...]), and the Evaluation [members, num_tasks] of the ``learnt`` first tasks of the sequences."""
        return self._call("measure", *self.arguments("measure", states, keys=self.program.put(keys), learnt=learnt))


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
