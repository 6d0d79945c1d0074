"""The runner's progress events: one frozen dataclass per kind, what its one callback to the outside world receives.

``jcomps.runner.experiment.run(..., progress_fn=...)`` calls ``progress_fn(event)`` on the host with one of the
``EVENTS`` (brax's ``progress_fn``, typed): the runner's own events say what a program is doing (``Start``,
``Compiling`` … ``Done``), the *member* events (``MEMBER_EVENTS``) carry the compiled programs' progress inside a
chunk, one member at a time (``jcomps.progress``'s phases, built by ``member_event``). Every event but ``Warned``
names its ``program``: the results entry of a program without a grid (``comps``, ``comps[learning_rate=0.001]``),
or ``"<label>, <n> grid points"`` for a program over several; its ``kind`` is its name in the ``jcomps.progress``
and JSON vocabulary.

With several processes (``jcomps.runner.distributed``) the member events of processes other than 0 cross to
process 0 as JSON (``to_json`` / ``from_json``); the runner's own events never leave their process. ``jcomps.console``
turns events into lines, TensorBoard and W&B logs. Nothing here imports JAX.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, Optional

from jcomps import progress


@dataclasses.dataclass(frozen=True)
class Start:
    """A program begins, before anything compiles. ``tasks``: the chosen tasks (empty: the family's list);
    ``padding``: members added to fill the devices (not reported); ``budget``: iterations per task; ``chunk``: tasks
    per chunk; ``start_task``: 0; ``members``: each member's name."""

    kind: ClassVar[str] = "start"
    program: str
    family: str
    sequence: str
    num_tasks: int
    tasks: tuple
    seeds: int
    grid_points: int
    padding: int
    devices: int
    budget: int
    chunk: int
    start_task: int
    members: tuple


@dataclasses.dataclass(frozen=True)
class Compiling:
    """One of the program's parts (``jcomps.runner.programs.PARTS``) is being compiled: ``part``, ``what`` (its name
    in words), for ``family`` and ``method``. ``learn`` compiles first and alone, the evaluation parts while the
    first task trains."""

    kind: ClassVar[str] = "compiling"
    program: str
    family: str
    method: str
    part: str
    what: str


@dataclasses.dataclass(frozen=True)
class StillCompiling(Compiling):
    """A compile still running, every ``jcomps.runner.programs.HEARTBEAT_SECONDS``: ``seconds`` so far."""

    kind: ClassVar[str] = "still_compiling"
    seconds: float = 0.0


@dataclasses.dataclass(frozen=True)
class Compiled(Compiling):
    """The part is ready after ``seconds`` (``trace_seconds`` of them tracing); ``cached``: whether it came from the
    persistent compile cache (``jcomps.runner.compile_cache``)."""

    kind: ClassVar[str] = "compiled"
    seconds: float = 0.0
    trace_seconds: float = 0.0
    cached: bool = False


@dataclasses.dataclass(frozen=True)
class Resumed:
    """The program continues from checkpoint ``step``: ``tasks_done`` of ``num_tasks``."""

    kind: ClassVar[str] = "resumed"
    program: str
    step: int
    tasks_done: int
    num_tasks: int


@dataclasses.dataclass(frozen=True)
class Warned:
    """Something was set aside (``message``), e.g. an unreadable checkpoint."""

    kind: ClassVar[str] = "warning"
    message: str


@dataclasses.dataclass(frozen=True)
class Evaluating:
    """The held-out meta-test and learnt-task evaluation after ``after_tasks`` tasks begins (0: the initial policies,
    measured after the first chunk); ``learnt``: how many learnt tasks it evaluates; ``adapts``: whether the
    meta-test adapts, or measures the zero-shot return only. ``HeldoutIteration`` events follow."""

    kind: ClassVar[str] = "evaluating"
    program: str
    after_tasks: int
    learnt: int
    adapts: bool = True


@dataclasses.dataclass(frozen=True)
class Evaluated:
    """The evaluations after ``after_tasks`` tasks took ``seconds``."""

    kind: ClassVar[str] = "evaluated"
    program: str
    after_tasks: int
    seconds: float


@dataclasses.dataclass(frozen=True)
class Chunk:
    """A chunk of tasks is done, for one results ``entry`` (after its checkpoint is written): tasks ``start`` to
    ``stop`` of ``num_tasks``; ``seeds`` of its members; ``metrics``: their ``continual.ChunkMetrics`` [members,
    chunk], ``per_task``: every task's so far [members, num_tasks]; ``learnt_tasks``: the ``continual.Evaluation``
    [members, num_tasks] of every task learnt (valid False where not evaluated), or None."""

    kind: ClassVar[str] = "chunk"
    program: str
    entry: str
    start: int
    stop: int
    num_tasks: int
    seeds: tuple
    metrics: Any
    per_task: Any
    learnt_tasks: Any = None


@dataclasses.dataclass(frozen=True)
class Done:
    """The program finished after ``seconds`` (over every session that ran it)."""

    kind: ClassVar[str] = "done"
    program: str
    seconds: float


@dataclasses.dataclass(frozen=True)
class Skipped:
    """The program had finished before: nothing to do."""

    kind: ClassVar[str] = "skipped"
    program: str


# --- The members' progress inside the compiled programs (``jcomps.progress``) ----------------------------------

NAN = float("nan")


@dataclasses.dataclass(frozen=True)
class Iteration:
    """An RL iteration of ``member`` on task index ``task``: its ``success_rate``, ``mean_return`` and the critic's
    explained variance ``value_ev`` (NaN without one)."""

    kind: ClassVar[str] = progress.ITERATION
    program: str
    member: int
    task: int
    iteration: int
    success_rate: float
    mean_return: float
    value_ev: float = NAN


@dataclasses.dataclass(frozen=True)
class MetaStep:
    """An outer update ``meta_step`` of ``meta_steps`` of ``member``'s meta step after task ``task``: its
    ``bc_loss``, and its health as means over the seen tasks (None where the method does not report it):
    ``value_l2``, ``value_ev``, ``adv_abs``, ``rho``, ``inner_gain`` (``jcomps.progress``)."""

    kind: ClassVar[str] = progress.META_STEP
    program: str
    member: int
    task: int
    meta_step: int
    meta_steps: int
    bc_loss: float
    value_l2: Optional[float] = None
    value_ev: Optional[float] = None
    adv_abs: Optional[float] = None
    rho: Optional[float] = None
    inner_gain: Optional[float] = None


@dataclasses.dataclass(frozen=True)
class CompressIteration:
    """An iteration ``compress_iteration`` of ``compress_iterations`` of ``pnc``'s compress phase: ``kl``."""

    kind: ClassVar[str] = progress.COMPRESS_ITERATION
    program: str
    member: int
    task: int
    compress_iteration: int
    compress_iterations: int
    kl: float


@dataclasses.dataclass(frozen=True)
class HeldoutIteration:
    """An iteration of ``member``'s held-out adaptation on held-out task ``heldout_task``."""

    kind: ClassVar[str] = progress.HELDOUT_ITERATION
    program: str
    member: int
    heldout_task: int
    heldout_iteration: int
    success_rate: float
    mean_return: float


@dataclasses.dataclass(frozen=True)
class TaskEnd:
    """A task of the continual loop ended (``continual.run_tasks``): ``task_iterations``, ``solved``."""

    kind: ClassVar[str] = progress.TASK
    program: str
    member: int
    task: int
    task_iterations: int
    solved: bool


@dataclasses.dataclass(frozen=True)
class MemberProgress:
    """Progress of a phase these classes do not name (a method's own, docs/extending.md): ``phase`` and its
    scalar ``metrics``."""

    kind: ClassVar[str] = "member_progress"
    program: str
    member: int
    phase: str
    metrics: dict


MEMBER_EVENTS = (Iteration, MetaStep, CompressIteration, HeldoutIteration, TaskEnd, MemberProgress)
"""The events of the compiled programs' progress, one member at a time; the ones that cross processes."""
EVENTS = (Start, Compiling, StillCompiling, Compiled, Resumed, Warned, Evaluating, Evaluated, Chunk, Done, Skipped,
          *MEMBER_EVENTS)
"""Every kind of event."""

_BY_PHASE = {cls.kind: cls for cls in MEMBER_EVENTS if cls is not MemberProgress}


def _fields(cls) -> tuple:
    return tuple(f.name for f in dataclasses.fields(cls))


def member_event(program: str, metrics: dict):
    """The event of a compiled program's progress call (``jcomps.progress``: ``phase``, ``member`` and its metrics
    as Python scalars or 0-d arrays): the phase's class with its fields, the metrics it does not name dropped; a
    phase without a class, a ``MemberProgress``."""
    values = {k: (v.item() if hasattr(v, "item") else v) for k, v in metrics.items() if k != "phase"}
    cls = _BY_PHASE.get(metrics["phase"])
    member = int(values.pop("member", 0))
    if cls is None:
        return MemberProgress(program=program, member=member, phase=metrics["phase"], metrics=values)
    known = {k: v for k, v in values.items() if k in _fields(cls)}
    for name in ("task", "iteration", "meta_step", "meta_steps", "compress_iteration", "compress_iterations",
                 "heldout_task", "heldout_iteration", "task_iterations"):
        if name in known:
            known[name] = int(known[name])
    return cls(program=program, member=member, **known)


def to_json(event) -> dict:
    """A member event as JSON-ready data (``{"event": kind, **fields}``), what crosses processes."""
    if not isinstance(event, MEMBER_EVENTS):
        raise TypeError(f"only member events cross processes, not {type(event).__name__}")
    return {"event": event.kind, **dataclasses.asdict(event)}


def from_json(data: dict):
    """The member event ``to_json`` made."""
    data = dict(data)
    kind = data.pop("event")
    cls = MemberProgress if kind == MemberProgress.kind else _BY_PHASE[kind]
    return cls(**data)
