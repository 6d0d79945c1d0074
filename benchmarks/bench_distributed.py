"""Throughput of one run spread over processes: the runner's chunk program as N processes × 1 device (started by
``scripts/local_cluster.sh``, JAX's multi-controller runtime over localhost) against 1 process × N devices, the
same members, in one run of this script.

Each case compiles the chunk program (``learn`` then ``evaluate_task`` for every task of a chunk; for several
processes also the gathering of its metrics to every process, as the runner does after every chunk), runs one
chunk to warm up, then times it ``--repeats`` times and counts the env steps (iterations × trajectories × T_max,
summed over members and tasks). Both cases compute the same numbers (the launcher gives every process the thread
pool of one process with N devices), so the work is identical. A third case runs N independent processes of
seeds / N members each side by side, without the runtime: what co-located processes cost by themselves. One line
per case as ``key=value`` pairs, then the ratios of steps/s (distributed over one process, independent over one
process, distributed over independent: the runtime's own cost).

    python benchmarks/bench_distributed.py [--family point_goal] [--method ppo_tl] [--seeds 8] [--tasks 2] \
        [--budget 40] [--repeats 3] [--processes 2]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
LAUNCHER = os.path.join(HERE, "..", "scripts", "local_cluster.sh")


def child(argv):
    """One process of a case: builds and times the chunk program; process 0 prints the figures as JSON."""
    from jcomps.runner import distributed, hostdevices

    parser = argparse.ArgumentParser()
    parser.add_argument("--child", required=True)
    parser.add_argument("--devices", type=int, required=True)
    distributed.add_args(parser)
    args = parser.parse_args(argv)
    cluster = distributed.settings(args)
    hostdevices.configure(args.devices)
    distributed.start(cluster)

    import dataclasses
    import time

    import jax
    import jax.numpy as jnp
    import numpy as np

    from jcomps import continual, envs, methods
    from jcomps.runner.members import num_devices, task_sequences
    from jcomps.runner.programs import Programs

    a = json.loads(args.child)
    family = envs.make(a["family"])
    config = methods.resolve_config(a["method"], a["family"], num_tasks=a["tasks"])
    collection = methods.collection(config)
    config = (dataclasses.replace(config, ppo=dataclasses.replace(config.ppo, budget=a["budget"]))
              if hasattr(config, "ppo") else dataclasses.replace(config, budget=a["budget"]))
    eval_config = continual.EvalConfig(backward_tasks=0, heldout_iterations=0)
    devices = num_devices(a["seeds"])
    program = Programs().get(a["method"], a["family"], config, eval_config, a["tasks"], devices)
    seeds = list(range(a["seeds"]))
    host_keys = jax.vmap(jax.random.PRNGKey)(jnp.asarray(seeds))  # init takes them whole, on every process
    bound = program.bind(task_sequences(family, "non-stationary", seeds, a["tasks"]),
                         np.arange(len(seeds), dtype=np.int32), host_keys, {}, jax.device_get(envs.held_out(family)))
    states = program.init(host_keys)

    def chunk():
        _, metrics = bound.learn_chunk(states, 0, program.chunk)
        return distributed.gather(metrics)  # on every process, as the runner's host loop needs them

    t0 = time.perf_counter()
    chunk()
    first_call = time.perf_counter() - t0
    times = []
    for _ in range(a["repeats"]):
        t0 = time.perf_counter()
        metrics = chunk()
        times.append(time.perf_counter() - t0)
    steps = int(np.sum(metrics.task.iterations)) * collection.num_trajectories * family.max_steps
    if distributed.is_writer():
        print(json.dumps({"processes": jax.process_count(), "devices": devices, "steps": steps,
                          "seconds": min(times), "first_call_s": first_call}), flush=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--family", default="point_goal")
    parser.add_argument("--method", default="ppo_tl")
    parser.add_argument("--seeds", type=int, default=8)
    parser.add_argument("--tasks", type=int, default=2)
    parser.add_argument("--budget", type=int, default=40)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--processes", type=int, default=2)
    args = parser.parse_args()
    from jcomps.runner import hostdevices

    n = args.processes
    payload = json.dumps({k: getattr(args, k) for k in ("family", "method", "seeds", "tasks", "budget", "repeats")})
    me = os.path.abspath(__file__)
    # The same XLA:CPU thread pool in both cases (the launcher's default: one process with n devices).
    env = dict(os.environ, NPROC=os.environ.get("NPROC", str(hostdevices.cores() + n)), PYTHON=sys.executable)
    cases = [("one_process", [sys.executable, me, "--child", payload, "--devices", str(n)]),
             ("distributed", ["bash", LAUNCHER, str(n), "--", me, "--child", payload, "--devices", "1"])]
    rates = []
    for name, cmd in cases:
        out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=1800)
        if out.returncode != 0:
            sys.exit(f"{name} failed:\n{out.stderr[-3000:]}")
        r = _figures(out.stdout)
        rates.append(r["steps"] / r["seconds"])
        print(f"family={args.family} method={args.method} members={args.seeds} case={name} "
              f"processes={r['processes']} devices={r['devices']} env_steps={r['steps']} seconds={r['seconds']:.2f} "
              f"env_steps_per_s={rates[-1]:.0f} first_call_s={r['first_call_s']:.1f}", flush=True)
    # The same split without the runtime: n independent processes of seeds / n members each, side by side. What
    # co-located processes cost by themselves (their XLA thread pools compete for the cores), apart from the
    # runtime's exchanges.
    part = json.dumps({**json.loads(payload), "seeds": args.seeds // n})
    procs = [subprocess.Popen([sys.executable, me, "--child", part, "--devices", "1"], env=env, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE) for _ in range(n)]
    outs = [p.communicate(timeout=1800) for p in procs]
    if any(p.returncode != 0 for p in procs):
        sys.exit("independent processes failed:\n" + "".join(err[-2000:] for _, err in outs))
    figures = [_figures(stdout) for stdout, _ in outs]
    steps, seconds = sum(f["steps"] for f in figures), max(f["seconds"] for f in figures)
    rates.append(steps / seconds)
    print(f"family={args.family} method={args.method} members={args.seeds} case=independent processes={n} "
          f"devices=1 env_steps={steps} seconds={seconds:.2f} env_steps_per_s={rates[-1]:.0f}", flush=True)
    print(f"family={args.family} method={args.method} members={args.seeds} "
          f"ratio_{n}_processes_to_1_process={rates[1] / rates[0]:.3f} "
          f"ratio_{n}_independent_processes_to_1_process={rates[2] / rates[0]:.3f} "
          f"ratio_distributed_to_independent={rates[1] / rates[2]:.3f}", flush=True)


def _figures(stdout: str) -> dict:
    return json.loads([line for line in stdout.splitlines() if line.startswith("{")][-1])


if __name__ == "__main__":
    if "--child" in sys.argv:
        child(sys.argv[1:])
    else:
        main()
