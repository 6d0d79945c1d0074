"""Runs spread over several processes (``jcomps.runner.distributed``): options, cluster detection and the progress relay
in-process; then real runs of two local processes with one CPU device each (``scripts/local_cluster.sh``, and the
SLURM script under a stand-in ``srun``) against one process with two devices: the same per-task results, array
for array; a process killed after the first checkpoint, the other stopping by itself and both resumed; the exit
codes of a missing coordinator and of a resume with another process count. Every process runs under a timeout, so
a hang fails the test instead of blocking CI.

Float results depend on XLA:CPU's intra-op thread pool size (``NPROC``): every process here sizes its own
(``jcomps.runner.hostdevices``), the reference with its 2 devices, the processes of a run as one process with all their
devices (``JCOMPS_LOCAL_PROCESSES``, which the launcher sets).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from jcomps.runner import distributed, events, hostdevices

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPT = os.path.join(ROOT, "experiments", "run_sequence.py")
LAUNCHER = os.path.join(ROOT, "scripts", "local_cluster.sh")
SBATCH = os.path.join(ROOT, "scripts", "slurm_study.sbatch")
TIMEOUT = 240
"""Seconds any one command of these tests may take (a tiny run takes well under a minute)."""

GRID = ["--methods", "ppo_tl", "--grid", "learning_rate=0.001,0.0003", "--num-tasks", "2", "--seeds", "2",
        "--chunk-tasks", "2"]
"""The 2-point grid run; the comps and ppo_tl run is ``conftest``'s ``full_run`` (3 tasks, 2 seeds, chunks of 1)."""


def _free_port(candidates=(0,)) -> int:
    """A port free on localhost now (0: any the system picks; else the first of ``candidates`` that binds)."""
    for port in candidates:
        with socket.socket() as s:
            try:
                s.bind(("localhost", port))
            except OSError:
                continue
            return s.getsockname()[1]
    raise RuntimeError("no free port")


def _env(**extra) -> dict:
    """The test session's environment without its thread pool size (each process sizes its own), the launcher's
    Python."""
    env = dict(os.environ, PYTHON=sys.executable, **extra)
    env.pop("NPROC", None)
    return env


def _group(cmd: list, env: dict | None = None) -> subprocess.Popen:
    """``cmd`` started in a process group of its own (a launcher's processes die with it on a timeout)."""
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env=_env() if env is None else env)


def _finish(procs: list, timeout: float = TIMEOUT) -> list:
    """Every process's (stdout, stderr); a process group still there after ``timeout`` is killed, whole."""
    try:
        return [p.communicate(timeout=timeout) for p in procs]
    finally:
        _kill(procs)


def _kill(procs: list):
    for p in procs:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


def _run(cmd: list, env: dict | None = None) -> subprocess.CompletedProcess:
    p = _group(cmd, env)
    (out, err), = _finish([p])
    return subprocess.CompletedProcess(cmd, p.returncode, out, err)


def _same_results(a, b):
    """Every array of every results entry of run directories ``a`` and ``b`` equal (wall seconds aside)."""
    entries = sorted(os.listdir(os.path.join(a, "raw")))
    assert [e for e in entries if e.endswith(".npz")], f"{a} has no results"
    assert entries == sorted(os.listdir(os.path.join(b, "raw")))
    for entry in entries:
        if not entry.endswith(".npz"):
            continue
        with np.load(os.path.join(a, "raw", entry)) as fa, np.load(os.path.join(b, "raw", entry)) as fb:
            assert fa.files == fb.files
            for key in fa.files:
                if key != "seconds":
                    np.testing.assert_array_equal(fa[key], fb[key], err_msg=f"{entry} {key}")


@pytest.fixture(scope="module")
def grid_reference(tiny_run, tiny_options):
    """The 2-point grid in this process (two host devices, the session's thread pool: cores + 2)."""
    return tiny_run(tiny_options + GRID, "one_process_grid")


# --- options and detection -------------------------------------------------------------------------------------

def _args(*argv):
    parser = argparse.ArgumentParser()
    distributed.add_args(parser)
    return parser.parse_args(list(argv))


def test_settings_from_options_and_cluster_managers():
    assert distributed.settings(_args(), environ={}) == distributed.Cluster()
    c = distributed.settings(_args("--coordinator", "node1:1234", "--num-processes", "4", "--process-id", "3",
                                   "--heartbeat-timeout", "20"), environ={})
    assert (c.num_processes, c.process_id, c.coordinator, c.heartbeat_timeout, c.distributed) == (4, 3, "node1:1234",
                                                                                                  20, True)
    slurm = {"SLURM_JOB_ID": "7", "SLURM_STEP_NUM_TASKS": "8", "SLURM_PROCID": "5", "CUDA_VISIBLE_DEVICES": "2,3"}
    c = distributed.settings(_args(), environ=slurm)
    assert (c.detected, c.num_processes, c.process_id, c.coordinator, c.local_device_ids) == ("slurm", 8, 5, None,
                                                                                              (0, 1))
    # The batch script itself (no srun step), or a one-task step, is one process.
    assert distributed.detect({"SLURM_JOB_ID": "7", "SLURM_NTASKS": "8", "SLURM_PROCID": "0"}) is None
    assert distributed.detect({**slurm, "SLURM_STEP_NUM_TASKS": "1"}) is None
    assert distributed.detect({"OMPI_COMM_WORLD_SIZE": "2", "OMPI_COMM_WORLD_RANK": "1"}) == ("ompi", 2, 1)
    assert distributed.local_device_ids({}) is None


@pytest.mark.parametrize("argv, message", [
    (("--coordinator", "h:1", "--num-processes", "2"), "--process-id missing"),
    (("--num-processes", "2", "--process-id", "0"), "--coordinator missing"),
    (("--coordinator", "h", "--num-processes", "2", "--process-id", "0"), "--coordinator must be HOST:PORT"),
    (("--coordinator", "h:99999", "--num-processes", "2", "--process-id", "0"), "a port 1 to 65535"),
    (("--coordinator", "h:1", "--num-processes", "2", "--process-id", "2"), r"--process-id must be in \[0, 1\]"),
    (("--coordinator", "h:1", "--num-processes", "0", "--process-id", "0"), "--num-processes must be >= 1"),
    (("--heartbeat-timeout", "0",), "--heartbeat-timeout must be"),
])
def test_settings_reject_bad_options(argv, message):
    with pytest.raises(ValueError, match=message):
        distributed.settings(_args(*argv), environ={})


def test_thread_pool_of_processes_sharing_a_machine():
    """Several processes of a run on one machine size XLA:CPU's pool as one process with all their devices (float
    rounding depends on it); a pool the user set is kept; a bad count is refused naming the variable."""
    cores = hostdevices.cores()
    assert hostdevices.environment(2, {})["NPROC"] == str(cores + 2)
    assert hostdevices.environment(1, {hostdevices.LOCAL_PROCESSES: "2"})["NPROC"] == str(cores + 2)
    assert hostdevices.environment(1, {hostdevices.LOCAL_PROCESSES: "2", "NPROC": "7"})["NPROC"] == "7"
    with pytest.raises(ValueError, match="JCOMPS_LOCAL_PROCESSES must be an integer >= 1"):
        hostdevices.environment(1, {hostdevices.LOCAL_PROCESSES: "0"})


def test_old_numpy_checkpoints_restore_into_sharded_states(tmp_path):
    """Checkpoints written before runs spread over processes held the states as NumPy arrays; they restore into
    the sharded states a run now saves and restores."""
    import jax
    from jax.sharding import NamedSharding, PartitionSpec

    from jcomps.runner import checkpoint

    old = {"states": {"00000": np.arange(8, dtype=np.float32).reshape(2, 4)}, "per_task": {"00000": np.ones(3)},
           "heldout": {"00000": np.ones(2)}, "counters": {"next_chunk": np.int64(1), "seconds": np.float64(2.5)}}
    checkpoint.Checkpoints(str(tmp_path / "c")).save(1, old)
    mesh = jax.make_mesh((2,), ("seed",), devices=jax.devices()[:2])
    states = jax.device_put(np.zeros((2, 4), np.float32), NamedSharding(mesh, PartitionSpec("seed")))
    like = checkpoint.record({"w": states}, np.zeros(3), np.zeros(2), 0, 0.0)
    step, tree = checkpoint.Checkpoints(str(tmp_path / "c")).restore_latest(like, warn=pytest.fail)
    assert step == 1 and tree["states"]["00000"].sharding == states.sharding
    np.testing.assert_array_equal(np.asarray(tree["states"]["00000"]), old["states"]["00000"])
    assert int(tree["counters"]["next_chunk"]) == 1 and float(tree["counters"]["seconds"]) == 2.5


def test_runtime_failures_are_told_from_local_errors():
    import jax

    assert distributed.runtime_failure(ValueError("UNKNOWN: Gloo AllGather failed: [pair.cc:538] Read error "
                                                  "[127.0.0.1]:4524: Connection reset by peer"))
    assert distributed.runtime_failure(jax.errors.JaxRuntimeError("DEADLINE_EXCEEDED: barrier timed out"))
    assert not distributed.runtime_failure(OSError(28, "No space left on device"))
    assert not distributed.runtime_failure(AssertionError("sync_global_devices name mismatch ('a')"))


class _Store:
    """The key-value store of JAX's distributed client, in memory."""

    def __init__(self):
        self.values = {}

    def key_value_set(self, key, value, allow_overwrite=False):
        assert allow_overwrite or key not in self.values
        self.values[key] = value

    def key_value_try_get(self, key):
        if key not in self.values:
            raise KeyError(key)
        return self.values[key]


def test_relay_hands_every_members_progress_to_process_zero(monkeypatch):
    monkeypatch.setattr(distributed, "_process_index", lambda: 1)
    store, shown = _Store(), []
    relay = distributed.Relay(interval=3600, client=store)
    merger = distributed.Merger(shown.append, num_processes=2, interval=3600, client=store)
    start = start_event()
    merger(start)  # process 0's own events pass straight through
    relay(start)  # process 0 has the runner's events: not relayed
    iteration = lambda i: events.Iteration(program="p", member=1, task=0, iteration=i, success_rate=0.5,  # noqa: E731
                                           mean_return=-1.0, value_ev=0.5)
    for i in range(3):
        relay(iteration(i))
    held = events.HeldoutIteration(program="p", member=1, heldout_task=2, heldout_iteration=4, success_rate=0.0,
                                   mean_return=-2.0)
    relay(held)
    merger.poll()  # nothing published yet
    relay.publish()
    merger.poll()
    merger.poll()  # each event once, the newest of each kind per member, typed again
    assert shown[0] is start and shown[1:] == [iteration(2), held]
    relay(iteration(3))
    relay(events.Iteration(program="p", member=2, task=0, iteration=0, success_rate=0.0, mean_return=-1.0))
    relay.close()
    merger.close()
    assert shown[-2] == iteration(3)
    assert shown[-1].member == 2 and np.isnan(shown[-1].value_ev)  # a default crosses too (NaN: no critic)


def test_member_events_come_from_the_compiled_programs_progress_and_cross_as_json():
    metrics = {"phase": "iteration", "member": np.int32(2), "task": np.int32(1), "iteration": np.int32(7),
               "success_rate": np.float32(0.25), "mean_return": np.float32(-3.5), "value_ev": np.float32(0.5),
               "a_method_own_metric": np.float32(1.0)}
    event = events.member_event("comps", metrics)
    assert event == events.Iteration("comps", member=2, task=1, iteration=7, success_rate=0.25, mean_return=-3.5,
                                     value_ev=0.5)
    assert type(event.iteration) is int and type(event.success_rate) is float
    assert events.from_json(json.loads(json.dumps(events.to_json(event)))) == event
    # A phase without a class of its own (a method's, docs/extending.md) keeps its metrics.
    own = events.member_event("es_tl", {"phase": "es_generation", "member": np.int32(0), "fitness": np.float32(2.0)})
    assert own == events.MemberProgress("es_tl", member=0, phase="es_generation", metrics={"fitness": 2.0})
    assert events.from_json(json.loads(json.dumps(events.to_json(own)))) == own
    with pytest.raises(TypeError, match="only member events cross processes"):
        events.to_json(start_event())


def start_event():
    return events.Start(program="p", family="point_goal", sequence="non-stationary", num_tasks=1, tasks=(), seeds=1,
                        grid_points=1, padding=0, devices=1, budget=3, chunk=1, start_task=0, members=("p seed 0",))


_RELAY_CHILD = r"""
import sys, time
from jcomps.runner import distributed, events, hostdevices
hostdevices.configure(1)
pid, port = int(sys.argv[1]), sys.argv[2]
distributed.start(distributed.Cluster(2, pid, f"localhost:{port}", coordinator_timeout=60, heartbeat_timeout=30))
shown = []
receiver = distributed.progress_receiver(shown.append, interval=0.2)
if pid == 1:
    for i in range(5):
        receiver(events.Iteration(program="p", member=3, task=0, iteration=i, success_rate=0.5, mean_return=-1.0))
    receiver.close()  # publishes what is left
distributed.barrier("published")
if pid == 0:
    receiver.close()
    print("SHOWN", shown, flush=True)
distributed.barrier("done")
"""


def test_relay_through_the_runtime():
    """The relay over JAX's own key-value store, between two real processes: process 0 shows process 1's members."""
    port = _free_port()
    procs = [_group([sys.executable, "-c", _RELAY_CHILD, str(i), str(port)]) for i in (0, 1)]
    outputs = _finish(procs)
    for p, (_, err) in zip(procs, outputs):
        assert p.returncode == 0, err[-3000:]
    assert ("SHOWN [Iteration(program='p', member=3, task=0, iteration=4, success_rate=0.5, mean_return=-1.0, "
            "value_ev=nan)]") in outputs[0][0]


# --- real runs of two processes --------------------------------------------------------------------------------

def test_grid_under_slurm(grid_reference, tiny_options, tmp_path):
    """The 2-point grid through scripts/slurm_study.sbatch, with a stand-in srun that starts the tasks here with
    the variables SLURM sets (JAX's SLURM detection finds the coordinator; no distributed options are given)."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "srun").write_text(
        "#!/bin/bash\n"
        "while [[ \"$1\" == --* ]]; do shift; done\n"
        "pids=()\n"
        "for ((i = 0; i < SLURM_NTASKS; i++)); do\n"
        "  SLURM_STEP_NUM_TASKS=$SLURM_NTASKS SLURM_PROCID=$i SLURM_LOCALID=$i SLURM_STEP_NODELIST=localhost "
        "\"$@\" &\n"
        "  pids+=($!)\n"
        "done\n"
        "rc=0\n"
        "for p in \"${pids[@]}\"; do wait $p || rc=$?; done\n"
        "exit $rc\n")
    (bin_dir / "srun").chmod(0o755)
    port = _free_port(range(61440, 65536))  # JAX takes the coordinator's port from the job id: 61440 + id % 4096
    # Both tasks share this machine, as the launcher's processes do (on a cluster each node has its own cores).
    env = _env(PATH=f"{bin_dir}:{os.environ['PATH']}", SLURM_JOB_ID=str(port - 61440), SLURM_NTASKS="2",
               SLURM_JOB_NODELIST="localhost", SLURM_SUBMIT_DIR=ROOT, JCOMPS_LOCAL_PROCESSES="2")
    out = tmp_path / "grid"
    proc = _run(["bash", SBATCH] + tiny_options + GRID + ["--devices", "1", "--out", str(out)], env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "process 1 of 2 (slurm)" in proc.stdout
    _same_results(grid_reference, out)


def _start(args, process_id: int, port: int, **env) -> subprocess.Popen:
    """Process ``process_id`` of a run of two on this machine."""
    return _group([sys.executable, SCRIPT] + args + ["--coordinator", f"localhost:{port}", "--num-processes", "2",
                                                     "--process-id", str(process_id), "--heartbeat-timeout", "30"],
                  _env(JCOMPS_LOCAL_PROCESSES="2", **env))


def test_two_processes_killed_and_resumed_give_the_results_of_one(full_run, full_run_argv, tmp_path):
    """comps and ppo_tl as two processes with one device each: process 1 killed once comps's first checkpoint is
    complete; process 0 stops by itself (exit code 3, saying what to do) instead of hanging; both resumed through
    the README's launcher, they finish with every per-task result of one process with two devices (``full_run``),
    array for array. Process 0 alone writes the report. Then a resume as one process is refused."""
    out = tmp_path / "two"
    port = _free_port()
    # A compile cache of the test's own, so that the resume loads what the killed run compiled, as a user's does.
    cache = {"JCOMPS_COMPILE_CACHE": str(tmp_path / "xla")}
    procs = [_start(full_run_argv + ["--devices", "1", "--out", str(out)], i, port, **cache) for i in (0, 1)]
    try:
        step = out / "checkpoints" / "comps" / "1"
        deadline = time.time() + TIMEOUT
        while not step.is_dir():
            assert time.time() < deadline and procs[0].poll() is None, "no first checkpoint"
            time.sleep(0.05)
        procs[1].send_signal(signal.SIGKILL)
        killed = time.time()
        (out0, err), = _finish(procs[:1], timeout=90)
        stopped = time.time() - killed
    finally:
        _kill(procs)
    assert procs[0].returncode == distributed.EXIT_PEER_LOST, err[-3000:]
    assert "lost the other processes" in err and "with --resume" in err
    assert stopped < 60, f"process 0 took {stopped:.0f} s to stop"
    assert "process 0 of 2: 1 of 2 devices" in out0 and not (out / "raw" / "comps.npz").exists()

    proc = _run(["bash", LAUNCHER, "2", "--", "--out", str(out), "--resume"], _env(**cache))
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "resumed from checkpoint 1" in proc.stdout
    assert "program ready" in proc.stdout and "from the compile cache" in proc.stdout  # comps's, compiled before
    _same_results(full_run, out)
    stored, ref = (json.loads((d / "run.json").read_text()) for d in (out, full_run))
    assert stored.pop("processes") == 2 and ref.pop("processes") == 1
    assert stored == ref  # devices 2 in both
    assert proc.stdout.count("mean iterations-to-success per task") == 1  # the report: process 0 alone
    assert (out / "results.json").exists() and (out / "significance.md").exists()

    proc = _run([sys.executable, SCRIPT, "--out", str(out), "--resume"])
    assert proc.returncode == 2
    assert "processes: run has 2, asked 1 (each process restores its own members: resume with --num-processes 2)" \
        in proc.stderr


def test_unreachable_coordinator_exits_2_naming_it():
    port = _free_port()
    began = time.time()
    proc = _run([sys.executable, SCRIPT, "--coordinator", f"localhost:{port}", "--num-processes", "2",
                 "--process-id", "1", "--coordinator-timeout", "2", "--out", "unused"])
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert f"coordinator at localhost:{port} within --coordinator-timeout 2 s" in proc.stderr
    assert time.time() - began < 60


def test_bad_distributed_option_exits_2():
    proc = _run([sys.executable, SCRIPT, "--coordinator", "localhost", "--num-processes", "2", "--process-id", "0"])
    assert proc.returncode == 2
    assert "--coordinator must be HOST:PORT" in proc.stderr


def test_tools_that_read_runs_work_on_process_zero_alone(merge_runs, tmp_path, capsys):
    """report.py, merge_runs.py and render.py started as several processes: process 0 does the work (it needs no
    runtime), the others say so and leave the directory alone."""
    merge_runs.main([str(tmp_path / "merged"), str(tmp_path / "a"), "--coordinator", "localhost:1",
                     "--num-processes", "2", "--process-id", "1"])
    out = capsys.readouterr().out
    assert "process 1 of 2:" in out and "runs on process 0 only" in out
    assert not (tmp_path / "merged").exists()
    with pytest.raises(SystemExit) as exit_info:  # bad options are refused as everywhere
        merge_runs.main([str(tmp_path / "merged"), str(tmp_path / "a"), "--process-id", "1"])
    assert exit_info.value.code == 2
    assert "--coordinator, --num-processes missing" in capsys.readouterr().err
