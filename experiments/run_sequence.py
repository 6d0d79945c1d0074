"""Run continual-learning methods over a task sequence and report iterations-to-success.

    python experiments/run_sequence.py                      # PPO+TL on 5 Point Goal tasks, 2 seeds (CPU, minutes)
    python experiments/run_sequence.py --family cheetah_vel --num-tasks 40 --seeds 6 --budget 500

Every method hyperparameter is an option (``--help`` lists them, derived from the config dataclasses).
Seeds run as one vmapped, jitted program per method. Writes ``results.json`` to the run directory.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

import jax
import numpy as np

from jcomps import cli, continual, envs, methods


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--family", default="point_goal", choices=envs.FAMILIES)
    parser.add_argument("--sequence", default="non-stationary", choices=envs.SEQUENCE_KINDS)
    parser.add_argument("--methods", nargs="+", default=["ppo_tl"], choices=methods.METHODS)
    parser.add_argument("--seeds", type=int, default=2, help="number of seeds (a vmap axis)")
    parser.add_argument("--seed", type=int, default=0, help="first seed")
    parser.add_argument("--num-tasks", type=int, default=5, help="length of the sequence (a prefix of the list)")
    parser.add_argument("--out", default=None, help="run directory (default: runs/<family>-<time>)")
    cli.add_config_args(parser, [methods.config_class(m) for m in methods.METHODS])
    args = parser.parse_args(argv)
    if args.seeds < 1:
        parser.error(f"--seeds must be >= 1, got {args.seeds}")
    family = envs.make(args.family)
    if not 1 <= args.num_tasks <= len(family.task_values):
        parser.error(f"--num-tasks must be in [1, {len(family.task_values)}] for {args.family}, got {args.num_tasks}")
    try:
        args.configs = {m: cli.build_config(methods.config_class(m), args) for m in args.methods}
    except (ValueError, TypeError) as err:
        parser.error(str(err))
    for name, config in args.configs.items():
        if getattr(config, "max_tasks", args.num_tasks) < args.num_tasks:
            parser.error(f"--max-tasks {config.max_tasks} is smaller than --num-tasks {args.num_tasks} ({name} "
                         f"keeps one experience slot per task)")
    args.out = args.out or os.path.join("runs", f"{args.family}-{time.strftime('%Y%m%d-%H%M%S')}")
    if os.path.exists(os.path.join(args.out, "results.json")):
        parser.error(f"--out {args.out} already holds a run (results.json); choose another directory")
    return args


def main(argv=None):
    args = parse_args(argv)
    family = envs.make(args.family)
    seeds = list(range(args.seed, args.seed + args.seeds))
    task_values = np.stack([envs.sequence_values(family, args.sequence, s, args.num_tasks) for s in seeds])
    tasks = family.tasks(task_values.reshape(-1))
    tasks = jax.tree.map(lambda x: x.reshape((len(seeds), args.num_tasks) + x.shape[1:]), tasks)
    rngs = jax.vmap(jax.random.PRNGKey)(np.asarray(seeds))
    os.makedirs(args.out, exist_ok=True)
    results = {"family": args.family, "sequence": args.sequence, "seeds": seeds,
               "task_values": task_values.tolist(), "methods": {}}

    for name in args.methods:
        config = args.configs[name]
        method = methods.make(name, family, config)
        budget = config.ppo.budget_for(family)
        start = time.time()

        def progress(seed_index, task_index, metrics, name=name, start=start):
            print(f"[{name}] seed {seeds[int(seed_index)]} task {int(task_index) + 1}/{args.num_tasks}: "
                  f"iterations-to-success {int(metrics.iterations)} solved {bool(metrics.solved)} "
                  f"elapsed {time.time() - start:.0f}s", flush=True)

        print(f"[{name}] {args.family} {args.sequence}, {args.num_tasks} tasks, {len(seeds)} seeds, "
              f"budget {budget}; compiling...", flush=True)
        _, metrics = continual.run_seeds(method, tasks, rngs, progress=progress, tasks_per_seed=True)
        metrics = jax.device_get(metrics)
        if np.any(metrics.per_iteration.nonfinite > 0):
            seed, task, it = np.argwhere(metrics.per_iteration.nonfinite > 0)[0]
            print(f"error: [{name}] non-finite values (NaN/inf) at seed {seeds[seed]}, task {task}, iteration "
                  f"{it}; those updates were skipped", file=sys.stderr)
        its = np.asarray(metrics.iterations)
        valid = np.asarray(metrics.per_iteration.valid)
        mean_return = np.where(valid, metrics.per_iteration.mean_return, 0).sum(-1) / np.maximum(valid.sum(-1), 1)
        results["methods"][name] = {
            "config": dataclasses.asdict(config),
            "budget": budget,
            "iterations_to_success": its.tolist(),
            "solved": np.asarray(metrics.solved).tolist(),
            "mean_return_per_task": mean_return.tolist(),
            "seconds": time.time() - start,
        }
        print(f"[{name}] done in {time.time() - start:.0f}s. iterations-to-success (seeds x tasks):")
        for s, row in zip(seeds, its):
            print(f"  seed {s}: {row.tolist()}")
        print(f"  mean over seeds: {np.round(its.mean(0), 1).tolist()}  "
              f"all solved: {bool(np.all(metrics.solved))}", flush=True)

    with open(os.path.join(args.out, "results.json.tmp"), "w") as f:
        json.dump(results, f, indent=1)
    os.replace(os.path.join(args.out, "results.json.tmp"), os.path.join(args.out, "results.json"))
    print(f"results written to {os.path.join(args.out, 'results.json')}")


if __name__ == "__main__":
    main()
