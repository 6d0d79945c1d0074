"""Throughput of a multi-seed run on 1 and 2 (or more) host devices: the runner's own chunk program.

Each case runs in a fresh process (the host device count must be set before JAX starts): it compiles the
runner's chunk program for a method, runs one chunk to warm up, then times the same chunk again and counts
the env steps it made (iterations × trajectories × T_max, summed over seeds and tasks). One line per case as
``key=value`` pairs, then the ratio to one device.

    python benchmarks/bench_devices.py [--family point_goal] [--method ppo_tl] [--seeds 4] [--tasks 2]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

from jcomps.runner import hostdevices

CHILD = r"""
import dataclasses, json, sys, time
import jax, jax.numpy as jnp, numpy as np
from jcomps import continual, envs, methods
from jcomps.runner.members import num_devices, task_sequences
from jcomps.runner.programs import Programs
a = json.loads(sys.argv[1])
family = envs.make(a["family"])
config = methods.config_class(a["method"])()
config = dataclasses.replace(config, ppo=dataclasses.replace(config.ppo, budget=a["budget"]))
eval_config = continual.EvalConfig(backward_tasks=0, heldout_iterations=0)
devices = num_devices(a["seeds"])
program = Programs().get(a["method"], a["family"], config, eval_config, a["tasks"], devices)
seeds = list(range(a["seeds"]))
keys = jax.vmap(jax.random.PRNGKey)(jnp.asarray(seeds))
bound = program.bind(task_sequences(family, "non-stationary", seeds, a["tasks"]),
                     np.arange(len(seeds), dtype=np.int32), keys, {}, jax.device_get(envs.held_out(family)))
states = program.init(keys)
t0 = time.perf_counter()
jax.block_until_ready(bound.learn_chunk(states, 0, program.chunk))
compile_s = time.perf_counter() - t0
times, steps = [], 0
for _ in range(a["repeats"]):
    t0 = time.perf_counter()
    _, m = jax.block_until_ready(bound.learn_chunk(states, 0, program.chunk))
    times.append(time.perf_counter() - t0)
    steps = int(np.sum(np.asarray(m.task.iterations))) * config.ppo.num_trajectories * family.max_steps
print(json.dumps({"devices": devices, "steps": steps, "seconds": min(times), "first_call_s": compile_s}))
"""


def main():
    from jcomps.runner import compile_cache

    compile_cache.from_environment()  # a second run of the benchmark loads its programs
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--family", default="point_goal")
    parser.add_argument("--method", default="ppo_tl")
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--tasks", type=int, default=2)
    parser.add_argument("--budget", type=int, default=40)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--devices", type=int, nargs="+", default=[1, 2])
    args = parser.parse_args()
    base = None
    for n in args.devices:
        env = hostdevices.environment(n)
        payload = json.dumps({k: getattr(args, k) for k in ("family", "method", "seeds", "tasks", "budget",
                                                             "repeats")})
        out = subprocess.run([sys.executable, "-c", CHILD, payload], env=env, capture_output=True, text=True)
        if out.returncode != 0:
            sys.exit(f"devices={n} failed:\n{out.stderr[-3000:]}")
        r = json.loads(out.stdout.strip().splitlines()[-1])
        rate = r["steps"] / r["seconds"]
        base = base or rate
        print(f"family={args.family} method={args.method} seeds={args.seeds} devices={r['devices']} "
              f"env_steps={r['steps']} seconds={r['seconds']:.2f} env_steps_per_s={rate:.0f} "
              f"first_call_s={r['first_call_s']:.1f} ratio_to_1_device={rate / base:.2f}", flush=True)


if __name__ == "__main__":
    main()
