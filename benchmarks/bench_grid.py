"""Throughput of a hyperparameter grid against the same number of seeds: the runner's own chunk programs.

One process, one device count: it compiles the runner's chunk program (``jcomps.runner.experiment``) for a 12-point
traced grid (learning_rate 0.01, 0.005, 0.001, 0.0001 × init_std 0.3, 0.5, 0.7) × 2 seeds, and for 24 seeds of
one config (the defaults), same family, method, tasks and budget; runs one chunk of each to warm up, then times
the chunk again (best of ``--repeats``, the two cases taking turns) and counts the env steps it made
(iterations × trajectories × T_max, summed over members and tasks). One ``key=value`` line per case, then the
ratio grid/seeds.

Under ``vmap`` a member that has reached the success threshold waits for the slowest member of its device, so
env steps/s also reflects how differently the members finish (``member_iterations`` is the sum of iterations,
``slot_iterations`` what the vmapped loops ran: members × the slowest member's iterations per device and task).

    python benchmarks/bench_grid.py [--family point_goal] [--method ppo_tl] [--tasks 2] [--budget 40]
"""

from __future__ import annotations

import argparse

from jcomps.runner import hostdevices


def main():
    from jcomps.runner import compile_cache

    compile_cache.from_environment()  # a second run of the benchmark loads its programs
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--family", default="point_goal")
    parser.add_argument("--method", default="ppo_tl")
    parser.add_argument("--tasks", type=int, default=2)
    parser.add_argument("--budget", type=int, default=40)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--devices", type=int, default=None, help="CPU host devices (default: one per core)")
    args = parser.parse_args()
    hostdevices.configure(args.devices or hostdevices.cores())

    import dataclasses
    import time

    import jax
    import jax.numpy as jnp
    import numpy as np

    from jcomps import continual, envs, methods
    from jcomps.runner import grid
    from jcomps.runner.members import layout, num_devices
    from jcomps.runner.programs import Programs

    family = envs.make(args.family)
    cls = methods.config_class(args.method)
    config = cls()
    config = dataclasses.replace(config, ppo=dataclasses.replace(config.ppo, budget=args.budget))
    if hasattr(config, "max_tasks"):
        config = dataclasses.replace(config, max_tasks=args.tasks)
    eval_config = continual.EvalConfig(backward_tasks=0, heldout_iterations=0)
    axes = grid.parse(["learning_rate=0.01,0.005,0.001,0.0001", "init_std=0.3,0.5,0.7"], {args.method: cls})
    cases = [("grid", grid.programs(args.method, config, axes)[0], 2),
             ("seeds", grid.programs(args.method, config, ())[0], 24)]
    prepared = {}
    for case, spec, seeds in cases:
        real = len(spec.points) * seeds
        devices = num_devices(real)
        _, member_seed, hparams = layout(spec, seeds, 0, devices)
        program = Programs().get(args.method, args.family, spec.config, eval_config, args.tasks, devices,
                                 spec.traced)
        values = np.stack([envs.sequence_values(family, "non-stationary", s, args.tasks) for s in member_seed])
        seqs = jax.tree.map(lambda x: x.reshape((len(member_seed), args.tasks) + x.shape[1:]),
                            family.tasks(values.reshape(-1)))
        keys = jax.vmap(jax.random.PRNGKey)(jnp.asarray(member_seed))
        bound = program.bind(seqs, np.arange(len(member_seed), dtype=np.int32), keys, hparams,
                             jax.device_get(envs.held_out(family)))
        states = program.init(keys, hparams)
        inputs = (bound, states)
        t0 = time.perf_counter()
        jax.block_until_ready(bound.learn_chunk(states, 0, program.chunk))
        prepared[case] = (spec, seeds, real, devices, program, inputs, time.perf_counter() - t0)
    # The cases take turns, so that a drift of the machine's speed touches both alike.
    times = {case: [] for case in prepared}
    metrics = {}
    for _ in range(args.repeats):
        for case, (_, _, _, _, program, inputs, _) in prepared.items():
            t0 = time.perf_counter()
            bound, states = inputs
            _, metrics[case] = jax.block_until_ready(bound.learn_chunk(states, 0, program.chunk))
            times[case].append(time.perf_counter() - t0)
    rates = {}
    for case, (spec, seeds, real, devices, _, _, first_call) in prepared.items():
        m = metrics[case]
        its = np.asarray(m.task.iterations)[:real]
        per_device = np.asarray(m.task.iterations).reshape(devices, -1, args.tasks)
        slot_its = int(np.sum(per_device.max(axis=1)) * per_device.shape[1])
        steps = int(its.sum()) * spec.config.ppo.num_trajectories * family.max_steps
        rates[case] = steps / min(times[case])
        print(f"case={case} family={args.family} method={args.method} points={len(spec.points)} seeds={seeds} "
              f"members={real} devices={devices} tasks={args.tasks} budget={args.budget} env_steps={steps} "
              f"member_iterations={int(its.sum())} slot_iterations={slot_its} seconds={min(times[case]):.2f} "
              f"median_s={float(np.median(times[case])):.2f} "
              f"env_steps_per_s={rates[case]:.0f} first_call_s={first_call:.1f}", flush=True)
    print(f"family={args.family} method={args.method} ratio={rates['grid'] / rates['seeds']:.2f}", flush=True)


if __name__ == "__main__":
    main()
