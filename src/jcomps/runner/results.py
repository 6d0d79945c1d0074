"""The raw results of a finished results entry (a method, or a method at a grid point): one typed structure,
written by the runner (``jcomps.runner.experiment``) and read back by the report (``jcomps.analysis.report``), here
only.

On disk, ``raw/<entry>.npz`` holds one array per leaf, named by its path in ``RawResults``
(``task.per_iteration.mean_return``, ``heldout.iterations``, ...). Files written before this structure existed
(keys ``iter.*``, ``heldout_return``, ...) are read too.
"""

from __future__ import annotations

import os
import typing
from typing import NamedTuple, Optional

import jax
import numpy as np

from jcomps.continual import Evaluation, HeldoutMetrics
from jcomps.methods.base import TaskMetrics
from jcomps.runner.files import RunError


class RawResults(NamedTuple):
    """Every metric of one results entry (numpy; S seeds, N tasks, P held-out measurements, H held-out tasks).

    Attributes:
      task: TaskMetrics: iterations and solved [S, N]; per_iteration fields [S, N, budget] (masked by valid).
      backward_returns: f32[S, N, k], the policy after task i on tasks i − 1 − d (``continual.ChunkMetrics``).
      backward_valid: bool[S, N, k].
      heldout: HeldoutMetrics with a leading [S, P] (curves [S, P, H, iterations + 1]; iterations [S, P, H]).
      heldout_after_tasks: i64[P], tasks learnt before each held-out measurement.
      seconds: wall time of the entry's program; devices: devices it ran on.
      backward_success: f32[S, N, k], the success rate of the backward-transfer episodes.
      learnt: Evaluation [S, N], the policy right after task i on task i (``continual.ChunkMetrics.learnt``).
      learnt_tasks: Evaluation [S, P, N], the policy of each held-out measurement on every task learnt by then
        (``continual.learnt_tasks``; valid False where not evaluated: tasks not yet learnt, and with
        ``learnt_eval=end`` every measurement before the last task).

    The last three are None in runs made before jcomps measured them (``results.load`` reads such runs).
    """

    task: TaskMetrics
    backward_returns: np.ndarray
    backward_valid: np.ndarray
    heldout: HeldoutMetrics
    heldout_after_tasks: np.ndarray
    seconds: float
    devices: int
    backward_success: Optional[np.ndarray] = None
    learnt: Optional[Evaluation] = None
    learnt_tasks: Optional[Evaluation] = None


def _leaves(prefix: str, x):
    if x is None:  # an optional part a method does not report (TaskMetrics.meta)
        return
    if hasattr(x, "_asdict"):
        for key, value in x._asdict().items():
            yield from _leaves(f"{prefix}{key}.", value)
    else:
        yield prefix[:-1], np.asarray(x)


def _build(cls, prefix: str, arrays: dict):
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name in cls._fields:
        tp = hints.get(name)
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if typing.get_origin(tp) is typing.Union and len(args) == 1:  # Optional[X]: present if any key is
            tp = args[0]
            if not any(key == f"{prefix}{name}" or key.startswith(f"{prefix}{name}.") for key in arrays):
                kwargs[name] = None
                continue
        if isinstance(tp, type) and hasattr(tp, "_fields"):
            kwargs[name] = _build(tp, f"{prefix}{name}.", arrays)
        else:
            kwargs[name] = arrays[f"{prefix}{name}"]
    return cls(**kwargs)


# Keys of the format before RawResults -> their path now.
_LEGACY = {"heldout_return": "heldout.mean_return", "heldout_success": "heldout.success_rate"}


def _upgrade(arrays: dict) -> dict:
    if "task.per_iteration.valid" in arrays:
        return _add_value_ev(_add_inner_gain(arrays))
    out = {}
    for key, value in arrays.items():
        if key.startswith("iter."):
            key = "task.per_iteration." + key[len("iter."):]
        out[_LEGACY.get(key, key)] = value
    shape = out["heldout.mean_return"].shape[:3]  # [S, P, H]: iterations-to-success was not measured then
    out.setdefault("heldout.iterations", np.zeros(shape, np.int32))
    out.setdefault("heldout.solved", np.zeros(shape, bool))
    return _add_value_ev(out)


def _add_value_ev(arrays: dict) -> dict:
    """The RL step's metrics of a run made before the critic's explained variance was reported: NaN."""
    if "task.per_iteration.value_ev" in arrays or "task.per_iteration.valid" not in arrays:
        return arrays
    shape = np.shape(arrays["task.per_iteration.valid"])
    return {**arrays, "task.per_iteration.value_ev": np.full(shape, np.nan, np.float32)}


def _add_inner_gain(arrays: dict) -> dict:
    """The meta step's health of a run made before the inner step's gain was measured: NaN gains."""
    for part in ("steps", "start", "end"):
        loss = arrays.get(f"task.meta.{part}.bc_loss")
        if loss is not None and f"task.meta.{part}.inner_gain" not in arrays:
            arrays = {**arrays, f"task.meta.{part}.inner_gain": np.full(np.shape(loss), np.nan, np.float32)}
    return arrays


def path(out: str, name: str) -> str:
    """Where entry ``name``'s raw results live in run directory ``out``."""
    return os.path.join(out, "raw", f"{name}.npz")


def partial_path(out: str, name: str) -> str:
    """Where the raw results of the tasks entry ``name`` has finished so far live while its run is unfinished."""
    return os.path.join(out, "raw", "partial", f"{name}.npz")


def _save(target: str, raw: RawResults) -> None:
    os.makedirs(os.path.dirname(target), exist_ok=True)
    with open(target + ".tmp", "wb") as f:
        np.savez(f, **dict(_leaves("", raw)))
    os.replace(target + ".tmp", target)


def _load(target: str, name: str) -> Optional[RawResults]:
    if not os.path.isfile(target):
        return None
    try:
        with np.load(target) as f:
            arrays = _upgrade({k: f[k] for k in f.files})
        raw = _build(RawResults, "", arrays)
    except Exception as err:  # noqa: BLE001 - any failure to read means the file is unusable
        raise RunError(f"{target} cannot be read ({type(err).__name__}: {err}); delete it to rerun {name}") from err
    return raw._replace(seconds=float(raw.seconds), devices=int(raw.devices))


def save(out: str, name: str, raw: RawResults) -> None:
    """Writes ``raw`` to ``raw/<name>.npz`` atomically and drops the entry's partial results."""
    _save(path(out, name), raw)
    partial = partial_path(out, name)
    if os.path.exists(partial):
        os.remove(partial)
        if not os.listdir(os.path.dirname(partial)):  # a finished run keeps raw/ as it always was
            os.rmdir(os.path.dirname(partial))


def load(out: str, name: str) -> Optional[RawResults]:
    """Entry ``name``'s raw results, or None if it has not finished; RunError if the file cannot be read."""
    return _load(path(out, name), name)


def save_partial(out: str, name: str, raw: RawResults) -> None:
    """Writes the raw results of the tasks finished so far (``raw`` covers them only) atomically; the runner
    rewrites them after every chunk, so that a run stopped before its end can still be reported."""
    _save(partial_path(out, name), raw)


def load_partial(out: str, name: str) -> Optional[RawResults]:
    """The raw results of the tasks entry ``name`` finished before its run stopped, or None if there are none."""
    return _load(partial_path(out, name), name)


def tasks_done(raw: RawResults) -> int:
    """How many tasks of the sequence ``raw`` covers."""
    return int(raw.task.iterations.shape[1])


def truncate(raw: RawResults, num_tasks: int) -> RawResults:
    """``raw`` cut to the first ``num_tasks`` tasks: their metrics, and the held-out measurements made after at
    most that many tasks."""
    if not 1 <= num_tasks <= tasks_done(raw):
        raise ValueError(f"num_tasks must be in [1, {tasks_done(raw)}], got {num_tasks}")
    keep = raw.heldout_after_tasks <= num_tasks
    first = lambda x: x[:, :num_tasks]  # noqa: E731 - None (no meta, an older run) stays None
    return raw._replace(task=jax.tree.map(first, raw.task), backward_returns=first(raw.backward_returns),
                        backward_valid=first(raw.backward_valid),
                        heldout=jax.tree.map(lambda x: x[:, keep], raw.heldout),
                        heldout_after_tasks=raw.heldout_after_tasks[keep],
                        backward_success=jax.tree.map(first, raw.backward_success),
                        learnt=jax.tree.map(first, raw.learnt),
                        learnt_tasks=jax.tree.map(lambda x: x[:, keep, :num_tasks], raw.learnt_tasks))

