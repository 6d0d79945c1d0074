"""The raw results of a finished results entry (a method, or a method at a grid point): one typed structure,
written by the runner (``jcomps.runner.experiment``) and read back by the report (``jcomps.analysis.report``), here
only.

A ``RawResults`` holds the runner's metric objects as they are, with a leading seed axis: the ``ChunkMetrics`` of
every task learnt and the ``Measurement`` of every held-out measurement. On disk, ``raw/<entry>.npz`` holds one
array per leaf, named by its path: the ``ChunkMetrics``' at the top (``task.per_iteration.mean_return``,
``backward_returns``, ``learnt.valid``), the ``Measurement``'s as ``heldout.*`` and ``learnt_tasks.*``, then
``heldout_after_tasks``, ``seconds`` and ``devices`` (the names these files have always had). Files written by
earlier versions are read through ``jcomps.migrations.upgrade_raw``.
"""

from __future__ import annotations

import os
import typing
from typing import NamedTuple, Optional

import jax
import numpy as np

from jcomps import migrations
from jcomps.continual import ChunkMetrics, Evaluation, HeldoutMetrics, Measurement
from jcomps.runner.files import RunError


class RawResults(NamedTuple):
    """Every metric of one results entry (numpy; S seeds, N tasks, P held-out measurements, H held-out tasks).

    Attributes:
      per_task: ChunkMetrics [S, N]: each task's TaskMetrics (iterations and solved [S, N], per_iteration fields
        [S, N, budget], masked by valid), its backward-transfer returns, validity and success rates [S, N, k] (the
        policy after task i on tasks i − 1 − d) and ``learnt`` (the policy right after task i on task i).
      measured: Measurement [S, P]: the held-out meta-test (curves [S, P, H, iterations + 1], iterations [S, P, H])
        and ``learnt`` [S, P, N], the policy of each measurement on every task learnt by then
        (``continual.learnt_tasks``; valid False where not evaluated: tasks not yet learnt, and with
        ``learnt_eval=end`` every measurement before the last task).
      heldout_after_tasks: i64[P], tasks learnt before each held-out measurement.
      seconds: wall time of the entry's program; devices: devices it ran on.

    ``per_task.backward_success``, ``per_task.learnt`` and ``measured.learnt`` are None in runs made before jcomps
    measured them (``load`` reads such runs).
    """

    per_task: ChunkMetrics
    measured: Measurement
    heldout_after_tasks: np.ndarray
    seconds: float
    devices: int


def _leaves(prefix: str, x):
    if x is None:  # an optional part a method does not report (TaskMetrics.meta), or an older run's
        return
    if hasattr(x, "_asdict"):
        for key, value in x._asdict().items():
            yield from _leaves(f"{prefix}{key}.", value)
    else:
        yield prefix[:-1], np.asarray(x)


def _arrays(raw: RawResults) -> dict:
    """The file's arrays by name (the module docstring)."""
    measured = raw.measured
    return {**dict(_leaves("", raw.per_task)), **dict(_leaves("heldout.", measured.heldout)),
            **dict(_leaves("learnt_tasks.", measured.learnt)), "heldout_after_tasks": raw.heldout_after_tasks,
            "seconds": np.asarray(raw.seconds), "devices": np.asarray(raw.devices)}


def _present(prefix: str, arrays: dict) -> bool:
    return any(key == prefix[:-1] or key.startswith(prefix) for key in arrays)


def _build(cls, prefix: str, arrays: dict):
    """``cls`` (a NamedTuple of arrays, nested) from the arrays named ``prefix`` + its fields' paths; an Optional
    field none of whose arrays is present is None."""
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name in cls._fields:
        tp = hints.get(name)
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if typing.get_origin(tp) is typing.Union and len(args) == 1:  # Optional[X]: present if any key is
            tp = args[0]
            if not _present(f"{prefix}{name}.", arrays):
                kwargs[name] = None
                continue
        if isinstance(tp, type) and hasattr(tp, "_fields"):
            kwargs[name] = _build(tp, f"{prefix}{name}.", arrays)
        else:
            kwargs[name] = arrays[f"{prefix}{name}"]
    return cls(**kwargs)


def _from_arrays(arrays: dict) -> RawResults:
    # Runs made before the learnt tasks' evaluations lack ``learnt_tasks``.
    learnt_tasks = _build(Evaluation, "learnt_tasks.", arrays) if _present("learnt_tasks.", arrays) else None
    heldout = _build(HeldoutMetrics, "heldout.", arrays)
    return RawResults(per_task=_build(ChunkMetrics, "", arrays), measured=Measurement(heldout, learnt_tasks),
                      heldout_after_tasks=arrays["heldout_after_tasks"], seconds=float(arrays["seconds"]),
                      devices=int(arrays["devices"]))


def path(out: str, name: str) -> str:
    """Where entry ``name``'s raw results live in run directory ``out``."""
    return os.path.join(out, "raw", f"{name}.npz")


def partial_path(out: str, name: str) -> str:
    """Where the raw results of the tasks entry ``name`` has finished so far live while its run is unfinished."""
    return os.path.join(out, "raw", "partial", f"{name}.npz")


def _save(target: str, raw: RawResults) -> None:
    os.makedirs(os.path.dirname(target), exist_ok=True)
    with open(target + ".tmp", "wb") as f:
        np.savez(f, **_arrays(raw))
    os.replace(target + ".tmp", target)


def _load(target: str, name: str) -> Optional[RawResults]:
    if not os.path.isfile(target):
        return None
    try:
        with np.load(target) as f:
            return _from_arrays(migrations.upgrade_raw({k: f[k] for k in f.files}))
    except Exception as err:  # noqa: BLE001 - any failure to read means the file is unusable
        raise RunError(f"{target} cannot be read ({type(err).__name__}: {err}); delete it to rerun {name}") from err


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
    return int(raw.per_task.task.iterations.shape[1])


def truncate(raw: RawResults, num_tasks: int) -> RawResults:
    """``raw`` cut to the first ``num_tasks`` tasks: their metrics, and the held-out measurements made after at
    most that many tasks."""
    if not 1 <= num_tasks <= tasks_done(raw):
        raise ValueError(f"num_tasks must be in [1, {tasks_done(raw)}], got {num_tasks}")
    keep = raw.heldout_after_tasks <= num_tasks
    measured = Measurement(jax.tree.map(lambda x: x[:, keep], raw.measured.heldout),
                           jax.tree.map(lambda x: x[:, keep, :num_tasks], raw.measured.learnt))
    return raw._replace(per_task=jax.tree.map(lambda x: x[:, :num_tasks], raw.per_task), measured=measured,
                        heldout_after_tasks=raw.heldout_after_tasks[keep])
