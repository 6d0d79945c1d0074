"""One run over many processes and hosts, with JAX's multi-controller runtime (``jax.distributed``).

Every process runs the same host loop and the same compiled programs; a program's members (``jcomps.runner.members``)
are sharded over the devices of *every* process (one global mesh over ``jax.devices()``), each process computing the
members on its own devices. The members never talk to each other, so the programs hold no collectives: processes
meet only where the host needs every member at once, through JAX's own machinery:

- ``gather``: the metrics after each chunk of tasks and each evaluation, one all-gather per event (a jitted
  identity to a replicated sharding: every process gets every member's metrics);
- the checkpoints: Orbax's multi-process checkpointing (``jcomps.runner.checkpoint``: every process writes and restores
  its own shards of the states, process 0 the metrics and counters, which every process holds whole);
- ``barrier``: before process 0 writes the run directory's files that the others then read.

Process 0 alone writes ``run.json``, results, plots and the significance table and prints; the others hand their
members' progress to it through the runtime's key-value store (``Relay`` / ``Merger``), so its progress lines
cover every process's members.

Starting: ``--coordinator HOST:PORT --num-processes N --process-id I`` (``add_args``), or none of them under a
cluster manager that ``jax.distributed.initialize()`` detects (a SLURM step or an Open MPI job of more than one
task: ``detect``). Without either a run is one process. ``start`` must run before JAX starts its
backend (like ``jcomps.runner.hostdevices.configure``). Failure: a process that loses its peers (one died or was killed:
a collective or a barrier fails) raises ``PeerLost``, which the runner turns into a message and exit code 3 at
once; a peer that stops answering without closing its connections (a host that froze) is caught by the runtime's
heartbeat, which stops every process within ``--heartbeat-timeout`` seconds with its own message. A process that
cannot reach the coordinator exits with code 2 naming the address it tried; process 0, whose peers never come,
is ended by JAX after ``--coordinator-timeout`` seconds with JAX's message (JAX's client aborts the process there;
the line before it says what it was waiting for).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import re
import socket
import sys
import threading
import time
import traceback
from typing import Callable, Mapping, Optional

EXIT_PEER_LOST = 3
"""The exit code of a process whose peers were lost (``PeerLost``)."""


class PeerLost(RuntimeError):
    """Another process of the run stopped (or cannot be reached): this one cannot go on."""


@dataclasses.dataclass(frozen=True)
class Cluster:
    """How this process joins a run of several processes (``settings``)."""

    num_processes: int = 1
    """Processes in the run (1: not distributed)."""
    process_id: int = 0
    """This process's index, 0 to ``num_processes - 1``; process 0 hosts the coordinator and writes the files."""
    coordinator: Optional[str] = None
    """``HOST:PORT`` of process 0's coordinator; None under a cluster manager (JAX finds it)."""
    detected: Optional[str] = None
    """The cluster manager the settings came from (``slurm``, ``ompi``), None when given as options."""
    coordinator_timeout: int = 300
    """Seconds a process waits for the coordinator and all processes to connect."""
    heartbeat_timeout: int = 100
    """Seconds after which a process that stopped answering is taken for dead and the run stopped."""
    local_device_ids: Optional[tuple] = None
    """The accelerators this process uses (under SLURM: every GPU ``CUDA_VISIBLE_DEVICES`` gives the task)."""

    @property
    def distributed(self) -> bool:
        return self.num_processes > 1


def add_args(parser: argparse.ArgumentParser) -> None:
    """The options that make a process one of several (see the module docstring)."""
    group = parser.add_argument_group("several processes (one run over many processes or hosts)")
    group.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                       help="address of process 0, which hosts JAX's coordinator (give with --num-processes and "
                            "--process-id; under SLURM or Open MPI with more than one task, leave all three out)")
    group.add_argument("--num-processes", type=int, default=None, metavar="N",
                       help="processes in the run; the members (seeds × grid points) are spread over all their "
                            "devices")
    group.add_argument("--process-id", type=int, default=None, metavar="I",
                       help="this process's index, 0 to N-1; process 0 writes the run directory's files and prints")
    group.add_argument("--coordinator-timeout", type=int, default=300, metavar="SECONDS",
                       help="how long to wait for the coordinator and every process to connect (default 300)")
    group.add_argument("--heartbeat-timeout", type=int, default=100, metavar="SECONDS",
                       help="a process silent this long is taken for dead and every process stops (default 100)")


def _int_env(environ: Mapping[str, str], name: str) -> Optional[int]:
    try:
        return int(environ[name])
    except (KeyError, ValueError):
        return None


def detect(environ: Optional[Mapping[str, str]] = None) -> Optional[tuple[str, int, int]]:
    """(cluster manager, processes, this process's index) when this process is one task of several under a
    cluster manager that ``jax.distributed.initialize()`` reads: a SLURM step (``srun``; the batch script itself
    is not a step) or an Open MPI job. None otherwise."""
    env = os.environ if environ is None else environ
    tasks = _int_env(env, "SLURM_STEP_NUM_TASKS")
    if "SLURM_JOB_ID" in env and tasks is not None and tasks > 1 and _int_env(env, "SLURM_PROCID") is not None:
        return "slurm", tasks, _int_env(env, "SLURM_PROCID")
    size = _int_env(env, "OMPI_COMM_WORLD_SIZE")
    if size is not None and size > 1 and _int_env(env, "OMPI_COMM_WORLD_RANK") is not None:
        return "ompi", size, _int_env(env, "OMPI_COMM_WORLD_RANK")
    return None


def local_device_ids(environ: Optional[Mapping[str, str]] = None) -> Optional[tuple]:
    """Under a cluster manager: every GPU that ``CUDA_VISIBLE_DEVICES`` gives this task (JAX numbers them from 0
    after CUDA applied the variable). JAX's own detection would give a SLURM task the single GPU of its local rank,
    wrong both for one task per node (all the node's GPUs) and for one task per GPU with device binding (the task
    sees one GPU, numbered 0). None without the variable (JAX's default)."""
    env = os.environ if environ is None else environ
    visible = [v for v in env.get("CUDA_VISIBLE_DEVICES", "").split(",") if v.strip()]
    return tuple(range(len(visible))) if visible else None


def settings(args: argparse.Namespace, environ: Optional[Mapping[str, str]] = None) -> Cluster:
    """The ``Cluster`` of this process from the options of ``add_args`` (``args``), else from a cluster manager
    (``detect``); raises ValueError naming the option when they are incomplete or out of range."""
    given = {"--coordinator": args.coordinator, "--num-processes": args.num_processes,
             "--process-id": args.process_id}
    for option, value in (("--coordinator-timeout", args.coordinator_timeout),
                          ("--heartbeat-timeout", args.heartbeat_timeout)):
        if value < 1:
            raise ValueError(f"{option} must be a whole number of seconds >= 1, got {value}")
    timeouts = dict(coordinator_timeout=args.coordinator_timeout, heartbeat_timeout=args.heartbeat_timeout)
    if all(v is None for v in given.values()):
        found = detect(environ)
        if found is None:
            return Cluster(**timeouts)
        manager, n, i = found
        return Cluster(n, i, None, manager, local_device_ids=local_device_ids(environ), **timeouts)
    missing = [option for option, value in given.items() if value is None]
    if missing:
        raise ValueError(f"{', '.join(missing)} missing: a process of several needs --coordinator HOST:PORT, "
                         f"--num-processes N and --process-id I together")
    host, _, port = args.coordinator.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"--coordinator must be HOST:PORT (a port 1 to 65535), got {args.coordinator!r}")
    if args.num_processes < 1:
        raise ValueError(f"--num-processes must be >= 1, got {args.num_processes}")
    if not 0 <= args.process_id < args.num_processes:
        raise ValueError(f"--process-id must be in [0, {args.num_processes - 1}] for --num-processes "
                         f"{args.num_processes}, got {args.process_id}")
    return Cluster(args.num_processes, args.process_id, args.coordinator, **timeouts)


def from_argv(argv: list[str], prog: str) -> Cluster:
    """``settings`` from a command line before the full parser runs (JAX must be initialised first); bad options
    exit with code 2 naming them, as argparse does."""
    parser = argparse.ArgumentParser(prog=prog, add_help=False)
    add_args(parser)
    args, _ = parser.parse_known_args(argv)
    try:
        return settings(args)
    except ValueError as err:
        parser.error(str(err))


def tool_process(args: argparse.Namespace, parser: argparse.ArgumentParser) -> bool:
    """For the scripts that read a finished or stopped run (report, merge, render), started as one of several
    processes (``add_args``'s options, or a cluster manager): whether this process does the work. They are quick
    host work, so process 0 does it all and joins no runtime; the others say so and do nothing. Bad options exit
    with code 2 naming them."""
    try:
        cluster = settings(args)
    except ValueError as err:
        parser.error(str(err))
    if cluster.process_id != 0:
        print(f"process {cluster.process_id} of {cluster.num_processes}: {parser.prog} runs on process 0 only; "
              f"nothing to do here", flush=True)
        return False
    return True


def start(cluster: Cluster) -> None:
    """Joins the run of ``cluster`` (``jax.distributed.initialize``; nothing for one process). Must run before JAX
    starts its backend. A coordinator that cannot be reached within ``coordinator_timeout``: exit code 2 naming
    the address."""
    if not cluster.distributed:
        return
    import jax

    address = cluster.coordinator or _detected_address(cluster)
    where = address or f"the address {cluster.detected} gives"
    # Said first, since a process whose peers never come is ended by JAX's own fatal error after the timeout.
    print(f"process {cluster.process_id} of {cluster.num_processes}: joining the run through the coordinator at "
          f"{where} (waiting up to {cluster.coordinator_timeout} s for every process)", file=sys.stderr, flush=True)
    # JAX's client aborts the process (a C++ fatal error, no Python exception) when it cannot reach the
    # coordinator, so a process other than 0 first checks that something listens there.
    if address and cluster.process_id != 0 and not _reachable(address, cluster.coordinator_timeout):
        _cannot_join(cluster, where, "nothing listens there")
    try:
        jax.distributed.initialize(cluster.coordinator, cluster.num_processes, cluster.process_id,
                                   local_device_ids=list(cluster.local_device_ids or []) or None,
                                   initialization_timeout=cluster.coordinator_timeout,
                                   heartbeat_timeout_seconds=cluster.heartbeat_timeout)
    except Exception as err:  # noqa: BLE001 - any failure to connect is reported the same way
        _cannot_join(cluster, where, _first_line(err))


def _detected_address(cluster: Cluster) -> Optional[str]:
    """The coordinator's address that JAX's cluster detection gives (SLURM: the step's first node and a port from
    the job id), None if it cannot tell."""
    try:
        from jax._src import clusters

        address, *_ = clusters.ClusterEnv.auto_detect_unset_distributed_params(
            None, cluster.num_processes, cluster.process_id, None, None, cluster.coordinator_timeout)
        return address
    except Exception:  # noqa: BLE001 - private API: without it, JAX's own detection still runs
        return None


def _reachable(address: str, timeout: float) -> bool:
    """Whether a TCP connection to ``HOST:PORT`` opens within ``timeout`` seconds (tried every half second)."""
    host, _, port = address.rpartition(":")
    deadline = time.monotonic() + timeout
    while True:
        try:
            socket.create_connection((host.strip("[]"), int(port)), timeout=2).close()
            return True
        except OSError:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.5)


def _cannot_join(cluster: Cluster, where: str, why: str) -> None:
    print(f"error: process {cluster.process_id} of {cluster.num_processes} could not join the run through the "
          f"coordinator at {where} within --coordinator-timeout {cluster.coordinator_timeout} s ({why}); check "
          f"that process 0 runs there and that every process was started", file=sys.stderr, flush=True)
    os._exit(2)  # not sys.exit: JAX's exit handler would wait for the processes that never came


def process_count() -> int:
    import jax

    return jax.process_count()


def is_writer() -> bool:
    """Whether this process writes the run directory's files and prints (process 0, or the only one)."""
    import jax

    return jax.process_index() == 0


def _first_line(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0][:300] if text else type(err).__name__


# How XLA's runtime words a failed status (gloo's failed collectives reach Python as a ValueError worded so).
_STATUS = re.compile(r"^(UNKNOWN|UNAVAILABLE|INTERNAL|DEADLINE_EXCEEDED|ABORTED|CANCELLED|FAILED_PRECONDITION): ")


def runtime_failure(err: BaseException) -> bool:
    """Whether ``err`` is a failure of JAX's runtime (a collective or barrier whose peer is gone), not a local
    error: a ``jax.errors.JaxRuntimeError``, or an error worded as an XLA status (``UNKNOWN: Gloo AllGather
    failed: ... Connection reset by peer``)."""
    import jax

    return isinstance(err, jax.errors.JaxRuntimeError) or bool(_STATUS.match(str(err)))


@contextlib.contextmanager
def exchange(what: str):
    """Around an exchange between processes (a collective, a barrier, a checkpoint's write): a failure of JAX's
    runtime (``runtime_failure``: a peer that is gone) becomes ``PeerLost``; any other error (a full disk,
    processes that took different paths) stays what it is, to be reported as such."""
    import jax

    try:
        yield
    except Exception as err:  # noqa: BLE001 - sorted below; anything else is raised as it is
        if jax.process_count() == 1 or not runtime_failure(err):
            raise
        raise PeerLost(f"lost the other processes during {what} ({_first_line(err)})") from err


def barrier(name: str) -> None:
    """Waits until every process gets here (nothing for one process); ``PeerLost`` if one cannot."""
    import jax

    if jax.process_count() == 1:
        return
    from jax.experimental import multihost_utils

    with exchange(f"the barrier {name!r}"):
        multihost_utils.sync_global_devices(name)


def all_agree(flag: bool, what: str) -> bool:
    """Whether ``flag`` holds on every process (``flag`` itself for one process)."""
    import jax
    import numpy as np

    if jax.process_count() == 1:
        return bool(flag)
    from jax.experimental import multihost_utils

    with exchange(what):
        return bool(np.all(multihost_utils.process_allgather(np.asarray(bool(flag)))))


def put(tree, sharding):
    """Host arrays (the same on every process) placed on ``sharding``'s devices, each process its own shards."""
    import jax
    import numpy as np

    if jax.process_count() == 1:
        return jax.device_put(tree, sharding)

    def one(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            return x  # already global
        host = np.asarray(x)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree.map(one, tree)


_REPLICATE: dict = {}


def gather(tree, what: str = "gathering metrics"):
    """``tree``'s arrays as NumPy arrays on every process: arrays sharded over several processes are gathered in
    one program (one all-gather per leaf, one launch for the tree). An empty array is made on the host (jax 0.10's
    ``device_get`` cannot assemble an empty array sharded over devices). ``PeerLost`` if a process is gone."""
    import jax
    import numpy as np
    from jax.sharding import NamedSharding, PartitionSpec

    leaves, treedef = jax.tree.flatten(tree)
    remote = [i for i, x in enumerate(leaves)
              if isinstance(x, jax.Array) and x.size > 0 and not x.is_fully_addressable]
    if remote:
        mesh = leaves[remote[0]].sharding.mesh
        replicate = _REPLICATE.get(mesh)
        if replicate is None:
            replicate = _REPLICATE[mesh] = jax.jit(lambda xs: xs, out_shardings=NamedSharding(mesh, PartitionSpec()))
        with exchange(what):
            whole = jax.block_until_ready(replicate([leaves[i] for i in remote]))
        for i, x in zip(remote, whole):
            leaves[i] = x
    host = [np.zeros(x.shape, x.dtype) if np.size(x) == 0 else np.asarray(jax.device_get(x)) for x in leaves]
    return jax.tree.unflatten(treedef, host)


def exit_now(code: int) -> None:
    """Ends a process of several at once (output flushed): Python's exit would first wait in JAX's shutdown barrier
    for the processes that are gone, until the heartbeat timeout, then abort."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def report_and_exit(err: BaseException, cluster: Cluster) -> None:
    """What a process of several does with an error it cannot go on from: says so and exits at once, so that the
    other processes see it gone (their next collective fails) instead of waiting for it. ``PeerLost``: exit code
    3; anything else: its traceback and code 1."""
    who = f"process {cluster.process_id} of {cluster.num_processes}"
    if isinstance(err, PeerLost):
        print(f"error: {who}: {err}. Another process stopped or cannot be reached, so every process stops; continue "
              f"the run from its last complete checkpoint by starting every process again with --resume",
              file=sys.stderr)
        exit_now(EXIT_PEER_LOST)
    print(f"error: {who} failed; stopping it so that the others stop too", file=sys.stderr)
    traceback.print_exception(err)
    exit_now(1)


# --- Progress from every process ------------------------------------------------------------------------------

_PREFIX = "jcomps/progress"


class Relay:
    """The ``progress_fn`` of a process other than 0: keeps the newest event of each kind per member and program,
    and publishes them to the runtime's key-value store at most every ``interval`` seconds (from a thread), so
    that process 0 (``Merger``) shows every member's progress. Relayed: the members' progress inside the compiled
    programs (``jcomps.runner.events.MEMBER_EVENTS``, as JSON); the runner's own events, the same on every
    process, are dropped (process 0 has them). ``close`` publishes what is left."""

    def __init__(self, interval: float = 2.0, client=None):
        from jcomps.runner import events  # imports JAX, which this module leaves until a process has joined

        self.events = events
        self.interval = interval
        self.client = client if client is not None else _client()
        self.key = f"{_PREFIX}/{_process_index()}"
        self.latest: dict = {}
        self.sequence = 0
        self.lock = threading.Lock()
        self.dirty = False
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()

    def __call__(self, event):
        if not isinstance(event, self.events.MEMBER_EVENTS):
            return
        with self.lock:
            self.sequence += 1
            key = (event.program, event.kind, event.member, getattr(event, "heldout_task", None))
            self.latest[key] = {**self.events.to_json(event), "_sequence": self.sequence}
            self.dirty = True

    def _loop(self):
        while not self.done.wait(self.interval):
            self.publish()

    def publish(self):
        with self.lock:
            if not self.dirty:
                return
            payload = json.dumps(list(self.latest.values()), default=float)
            self.dirty = False
        try:
            self.client.key_value_set(self.key, payload, allow_overwrite=True)
        except Exception:  # noqa: BLE001 - progress is best effort; the host loop reports a lost peer
            pass

    def close(self):
        self.done.set()
        self.thread.join()
        self.publish()


class Merger:
    """Process 0's side of ``Relay``: every ``interval`` seconds (from a thread) reads the other processes' newest
    events and hands those it has not seen to ``progress_fn``, together with process 0's own events (``__call__``),
    under one lock, so the progress lines cover every member."""

    def __init__(self, progress_fn: Callable[[object], None], num_processes: int, interval: float = 2.0,
                 client=None):
        from jcomps.runner import events  # as Relay's

        self.events = events
        self.progress_fn, self.interval = progress_fn, interval
        self.client = client if client is not None else _client()
        self.keys = [f"{_PREFIX}/{p}" for p in range(1, num_processes)]
        self.seen = dict.fromkeys(self.keys, 0)
        self.lock = threading.Lock()
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()

    def __call__(self, event):
        with self.lock:
            self.progress_fn(event)

    def _loop(self):
        while not self.done.wait(self.interval):
            self.poll()

    def poll(self):
        for key in self.keys:
            try:
                payload = self.client.key_value_try_get(key)
            except Exception:  # noqa: BLE001 - nothing published yet (or the peer is gone: the host loop says so)
                continue
            published = sorted(json.loads(payload), key=lambda e: e["_sequence"])
            with self.lock:
                for event in published:
                    if event["_sequence"] > self.seen[key]:
                        self.progress_fn(self.events.from_json({k: v for k, v in event.items()
                                                                if k != "_sequence"}))
                self.seen[key] = max([self.seen[key]] + [e["_sequence"] for e in published])

    def close(self):
        self.done.set()
        self.thread.join()
        self.poll()


def _client():
    from jax._src import distributed as jax_distributed

    return jax_distributed.global_state.client


def _process_index() -> int:
    import jax

    return jax.process_index()


def progress_receiver(progress_fn: Callable[[object], None], interval: float = 2.0):
    """The receiver this process hands the runner: ``progress_fn`` itself for one process; on process 0 of several
    a ``Merger`` around it, on the others a ``Relay`` (``progress_fn`` unused). ``close_receiver`` when the run
    ends."""
    if process_count() == 1:
        return progress_fn
    if is_writer():
        return Merger(progress_fn, process_count(), interval)
    return Relay(interval)


def close_receiver(receiver) -> None:
    """Ends ``progress_receiver``'s receiver on every process: the relays publish what is left, then (a barrier)
    process 0 shows it."""
    if isinstance(receiver, Relay):
        receiver.close()
    if process_count() > 1:
        barrier("progress published")
    if isinstance(receiver, Merger):
        receiver.close()
