"""Checkpoints of a run: Orbax, atomic, every piece of a program's state, readable back or set aside.

A checkpoint (``record``) holds the flat leaves of the members' states (parameters, optimiser states, experience
stores, rng, counters), the metrics so far and the run's counters, so a resumed run continues exactly where it
stopped (brax saves parameters only). An unreadable checkpoint is moved aside, never deleted, and the one before
it is tried.

The states are saved as the sharded arrays they are, so that a run of several processes (``jcomps.runner.distributed``)
uses Orbax's multi-process checkpointing: every process writes its own members' shards and restores them, process
0 writes the metrics and counters (NumPy arrays every process holds whole) and, once all are written, commits the
step (renames it into place), so a step is there whole or not at all.
"""

from __future__ import annotations

import errno
import os
import shutil
import time
from typing import Optional

import jax
import numpy as np

from jcomps.runner import distributed
from jcomps.runner.files import RunError


def flatten(tree) -> dict:
    """The leaves of ``tree`` by index (device arrays stay as they are, sharded; anything else becomes a NumPy
    array); empty arrays (e.g. backward transfer with ``--backward-tasks 0``) hold nothing and are left out, since
    Orbax refuses to save zero-size arrays."""
    return {f"{i:05d}": x if isinstance(x, jax.Array) else np.asarray(x)
            for i, x in enumerate(jax.tree.leaves(tree)) if np.size(x) > 0}


def unflatten(like, flat: dict):
    """The inverse of ``flatten`` (``flat`` checked against ``like`` by ``Checkpoints.restore_latest``)."""
    leaves, treedef = jax.tree.flatten(like)
    return jax.tree.unflatten(treedef, [flat[f"{i:05d}"] if np.size(x) > 0 else np.zeros(np.shape(x), x.dtype)
                                        for i, x in enumerate(leaves)])


def record(states, per_task, heldout, next_chunk: int, seconds: float) -> dict:
    """What a checkpoint holds: flat arrays of the states and the metrics so far, and the counters."""
    return {"states": flatten(states), "per_task": flatten(per_task), "heldout": flatten(heldout),
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
        """Writes checkpoint ``step`` (every process calls it; ``distributed.PeerLost`` if a process is gone). Too
        little free space for it ends in ``RunError`` before anything is written (the steps before it kept, so
        ``--resume`` continues from the last of them once there is space); a disk that fills while Orbax writes
        anyway (the estimate was short) ends in ``RunError`` too, after Orbax's threads have printed their
        tracebacks, with its temporary step removed where it can be."""
        import absl.logging

        need, free = self._space_needed(tree), shutil.disk_usage(self.directory).free
        if free < need:  # Orbax's writer threads fail noisily on a full disk: refuse before writing
            kept = self.manager.all_steps()
            raise RunError(f"no space left on the device for checkpoint step {step} in {self.directory} (about "
                           f"{need / 2**20:.1f} MiB needed, {free / 2**20:.1f} MiB free); free space there, then "
                           f"continue the run with --resume" + (f" (from its last checkpoint, step {max(kept)})"
                                                                 if kept else ""))
        verbosity = absl.logging.get_verbosity()
        absl.logging.set_verbosity(absl.logging.FATAL)  # Orbax logs its writer threads' failures, then raises
        try:
            with distributed.exchange(f"the writing of checkpoint step {step}"):
                self.manager.save(step, args=self.ocp.args.StandardSave(tree), force=True)
                self.manager.wait_until_finished()
        except distributed.PeerLost:
            raise
        except Exception as err:  # noqa: BLE001 - Orbax reports a full disk as ValueError(RESOURCE_EXHAUSTED)
            if not disk_full(err):
                raise
            for name in os.listdir(self.directory):
                if name.startswith(f"{step}.") and "tmp" in name:
                    shutil.rmtree(os.path.join(self.directory, name), ignore_errors=True)
            self._open()
            kept = self.manager.all_steps()
            raise RunError(f"no space left on the device writing checkpoint step {step} in {self.directory} "
                           f"({type(err).__name__}: {str(err)[:200]}); free space there, then continue the run "
                           f"with --resume" + (f" (from its last checkpoint, step {max(kept)})" if kept else "")
                           ) from None
        finally:
            absl.logging.set_verbosity(verbosity)

    def _space_needed(self, tree: dict) -> int:
        """Bytes a new step may take: a quarter more than the newest step on disk, or, for the first, a tenth more
        than the arrays and 128 KiB of Orbax's metadata (a tiny run's step takes 172 KB, 35 files)."""
        steps = self.manager.all_steps()
        if steps:
            newest = os.path.join(self.directory, str(max(steps)))
            size = sum(os.path.getsize(os.path.join(d, f)) for d, _, files in os.walk(newest) for f in files)
        else:
            leaves = jax.tree.leaves(tree)
            size = sum(np.asarray(x).nbytes if not isinstance(x, jax.Array) else x.nbytes for x in leaves)
            return int(size * 1.1) + 192 * 1024
        return int(size * 1.25) + 64 * 1024

    def restore_latest(self, like: dict, warn) -> Optional[tuple[int, dict]]:
        """The newest readable checkpoint (an unreadable one is set aside and reported through ``warn(message)``,
        and the one before it is tried). Device arrays in ``like`` are restored as device arrays with their
        sharding (each process its own shards), anything else as NumPy arrays.

        With several processes an unreadable step stops the run (``RunError``, naming it) instead: Orbax's restore
        ends in a barrier of every process, which a process that failed before it never reaches, so the processes
        cannot agree to try the step before; the user moves the step aside and resumes."""
        errors = []
        target = jax.tree.map(_target, like)
        for step in sorted(self.manager.all_steps(), reverse=True):
            try:
                with distributed.exchange(f"the reading of checkpoint step {step}"):
                    tree = self.manager.restore(step, args=self.ocp.args.StandardRestore(target))
                tree = jax.tree.map(lambda t, x: x if isinstance(t, jax.ShapeDtypeStruct) else np.asarray(x),
                                    target, tree)
                _check_like(target, tree)
            except distributed.PeerLost:
                raise
            except Exception as err:  # noqa: BLE001 - any failure to read means this checkpoint is unusable
                errors.append(f"step {step}: {type(err).__name__}: {str(err)[:300]}")
                if distributed.process_count() > 1:
                    raise RunError(f"checkpoint step {step} in {self.directory} cannot be read by process "
                                   f"{jax.process_index()} ({errors[-1]}); move {self.directory}/{step} out of the "
                                   f"way and resume every process again (they continue from the step before)"
                                   ) from None
                dest = self._set_aside(step)
                warn(f"checkpoint step {step} in {self.directory} cannot be read ({errors[-1]}); moved to {dest}")
                continue
            if errors:
                self._open()
            return step, tree
        if errors:
            raise RunError("no readable checkpoint (unreadable ones were moved to "
                           f"{self.directory}-unreadable): " + " | ".join(errors))
        return None


def disk_full(err: BaseException) -> bool:
    """Whether ``err`` says the disk (or the user's quota) is full: an OSError of ENOSPC or EDQUOT, or Orbax's and
    TensorStore's RESOURCE_EXHAUSTED."""
    if isinstance(err, OSError) and err.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    return "RESOURCE_EXHAUSTED" in str(err) or "No space left" in str(err)


def read_latest(directory: str, warn) -> Optional[tuple[int, dict]]:
    """The newest readable checkpoint in ``directory`` as saved (numpy arrays), read-only: nothing is written or
    moved; an unreadable step is reported through ``warn(message)`` and the one before it tried. None when the
    directory holds no checkpoint."""
    import absl.logging
    import orbax.checkpoint as ocp

    if not os.path.isdir(directory):
        return None
    verbosity = absl.logging.get_verbosity()
    absl.logging.set_verbosity(absl.logging.ERROR)  # Orbax announces read-only mode as a warning
    try:
        manager = ocp.CheckpointManager(os.path.abspath(directory), options=ocp.CheckpointManagerOptions(
            read_only=True, create=False, enable_async_checkpointing=False),
            item_handlers=ocp.StandardCheckpointHandler())
        for step in sorted(manager.all_steps(), reverse=True):
            try:
                # Every array onto this process's first device, whatever devices and processes wrote it.
                metadata = manager.item_metadata(step)
                local = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
                target = jax.tree.map(lambda m: jax.ShapeDtypeStruct(m.shape, m.dtype, sharding=local),
                                      getattr(metadata, "tree", metadata))
                return step, jax.tree.map(np.asarray, manager.restore(step, args=ocp.args.StandardRestore(target)))
            except Exception as err:  # noqa: BLE001 - any failure to read means this checkpoint is unusable
                warn(f"checkpoint step {step} in {directory} cannot be read ({type(err).__name__}: "
                     f"{str(err)[:300]}); trying the one before")
    finally:
        absl.logging.set_verbosity(verbosity)
    return None


def _target(x):
    """What Orbax restores a leaf of ``like`` into: a device array's shape, dtype and sharding, else NumPy."""
    if isinstance(x, jax.Array):
        return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=x.sharding)
    return np.asarray(x)


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
