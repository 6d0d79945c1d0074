"""CPU host devices for JAX: how many, and an intra-op thread pool that cannot deadlock. Call before JAX starts.

On a CPU, ``--xla_force_host_platform_device_count=N`` splits the machine into N JAX devices, so a vmapped seed
axis sharded over them keeps every core busy (XLA runs one program on about one core). One more setting is
needed for that to be safe: jaxlib's batched LAPACK kernels (the Cholesky and triangular solves inside MJX's
constraint solver, the QR of an orthogonal initialiser under ``vmap``) split the batch over XLA:CPU's intra-op
thread pool and wait for the parts *on a pool thread*. That pool has one thread per core, so with N devices on
N cores every pool thread can be waiting at once and nothing runs the parts: the process hangs at 0% CPU (seen
with jax 0.10.2 on 2 cores and 2 devices; gdb shows both ``tf_XLAEigen`` threads in ``jax::ParallelBatchMap``).
XLA sizes the pool from the ``NPROC`` environment variable when it is set, so :func:`configure` sets it to the
core count plus the device count: each device can have one kernel waiting and all cores still have a thread.
That covers jcomps' programs, where a device waits in at most one such kernel at a time (MJX calls them one
after another; initialisation runs seed by seed, unbatched, where the kernel runs inline). A program that runs
many independent batched LAPACK calls at once can still use up the pool. (jaxlib 0.11 reportedly builds this
parallel path out; we pin 0.10.2.)

The pool's size also moves float rounding: XLA:CPU's results differ in the last bits between ``NPROC=3`` and
``NPROC=4`` (seen on a PPO run). Runs are bit-for-bit reproducible for the same devices *and* pool; several
processes on one machine (``scripts/local_cluster.sh``) each get the pool one process with all the devices has
(``LOCAL_PROCESSES``), so that they give that process's results exactly.

>>> from jcomps import hostdevices
>>> hostdevices.configure(2)      # before the first ``import jax`` in the process
>>> import jax; jax.device_count()
2

This module imports nothing from JAX, so it can run first.
"""

from __future__ import annotations

import os
import sys
from typing import MutableMapping

DEVICE_FLAG = "--xla_force_host_platform_device_count"


def cores() -> int:
    """Cores this process may run on (its CPU affinity where the platform tells it)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


LOCAL_PROCESSES = "JCOMPS_LOCAL_PROCESSES"
"""Environment variable: how many processes of one run share this machine (``scripts/local_cluster.sh`` sets it),
each with the same device count; the pool is then sized as for one process with all their devices."""


def environment(devices: int, environ: MutableMapping[str, str] | None = None) -> dict[str, str]:
    """``environ`` (default ``os.environ``) updated for ``devices`` host devices: ``XLA_FLAGS`` with the device
    count (any earlier count replaced, other flags kept) and ``NPROC`` (the intra-op pool size: cores + devices,
    the devices of every process of the run on this machine when ``LOCAL_PROCESSES`` says there are several; a
    value the user set, or ``PORTABLE_NPROC``, is kept). Returns a new dict; nothing is changed."""
    if not isinstance(devices, int) or isinstance(devices, bool) or devices < 1:
        raise ValueError(f"devices must be an integer >= 1, got {devices!r}")
    env = dict(os.environ if environ is None else environ)
    flags = [f for f in env.get("XLA_FLAGS", "").split() if not f.startswith(DEVICE_FLAG)]
    env["XLA_FLAGS"] = " ".join(flags + [f"{DEVICE_FLAG}={devices}"])
    local = env.get(LOCAL_PROCESSES, "1")
    if not local.isdigit() or int(local) < 1:
        raise ValueError(f"{LOCAL_PROCESSES} must be an integer >= 1, got {local!r}")
    if "NPROC" not in env and "PORTABLE_NPROC" not in env:
        env["NPROC"] = str(cores() + devices * int(local))
    return env


def configure(devices: int) -> None:
    """Sets this process's environment for ``devices`` CPU host devices (see the module docstring). Must run
    before JAX creates its CPU backend; raises ``RuntimeError`` if that already happened."""
    if _backend_started():
        raise RuntimeError("jcomps.runner.hostdevices.configure must run before JAX starts its CPU backend "
                           "(call it before any JAX computation, ideally before `import jax`)")
    os.environ.update(environment(devices))


def _backend_started() -> bool:
    bridge = sys.modules.get("jax._src.xla_bridge")
    return bool(getattr(bridge, "_backends", None))
