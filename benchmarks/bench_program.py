"""Whole-program speed: env steps/s of the runner's chunk program against raw vmapped ``env.step``, same batch.

For each member count M (seeds, vmapped on one device) the script times, in one process:

- ``raw``: T_max steps of M × B fresh episodes of ``family.step`` in one jitted ``lax.scan``, precomputed
  actions (B = the method's trajectories per iteration): what the simulator alone costs;
- ``program``: the runner's own compiled chunk program (``jcomps.runner.programs.Programs``) for the method, with
  the family's default config, on the first ``--tasks`` tasks of the non-stationary sequence with budget
  ``--budget`` (no backward or held-out evaluation): rollouts, PPO updates, experience stores and meta steps;
  env steps = the iterations it ran × B × T_max;
- the parts of an iteration, each on its own: ``rollout`` (``acting.rollout``, policy sampling included, vmapped
  over the members) and ``update`` (``ppo.ppo_update``: the iteration's ``num_updates`` minibatch Adam steps,
  vmapped); ``other_s`` is what the program spent beyond iterations × (rollout + update): meta steps, stores,
  loop overhead, per task.

One line per member count as ``key=value`` pairs ending in ``ratio=<program env steps/s ÷ raw env steps/s>``
(the median over alternating timed repeats of the per-repeat ratio). On a CPU the process uses one host
device (XLA runs one program on about one core); on a GPU, the GPU.

    python benchmarks/bench_program.py [--family cheetah_vel] [--method comps] [--members 1 4] [--tasks 2]
        [--budget 40] [--repeats 3] [--no-parts]
"""

from __future__ import annotations

import argparse
import os
import time

from jcomps.runner import hostdevices


def _seconds(fn, *args):
    import jax

    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return time.perf_counter() - start, out


def bench(family_name: str, method: str, members: int, tasks: int, budget: int, repeats: int,
          parts: bool = True, compile_only: bool = False, wait_for: str | None = None,
          signal: str | None = None) -> str:
    import jax
    import numpy as np

    from jcomps import continual, envs, methods
    from jcomps.runner.members import method_keys, task_eval_keys, task_sequences
    from jcomps.runner.programs import Programs
    from jcomps.training import acting, ppo

    family = envs.make(family_name)
    config = methods.resolve_config(method, family, shared={"budget": budget}, num_tasks=tasks)
    B, T = config.ppo.num_trajectories, family.max_steps
    eval_config = continual.EvalConfig(backward_tasks=0, heldout_iterations=0)

    # The runner's chunk program, exactly as run_sequence.py builds it (one chunk = all the tasks).
    program = Programs().get(method, family_name, config, eval_config, tasks, 1)
    seeds = list(range(members))
    # Every member learns seed 0's sequence (the same work per member), bound as the runner binds a run's inputs.
    bound = program.bind(task_sequences(family, "non-stationary", [0] * members, tasks),
                         np.arange(members, dtype=np.int32), task_eval_keys(seeds), {},
                         jax.device_get(envs.held_out(family)))
    states = program.init(method_keys(seeds))
    chunk_args = (states, 0, program.chunk)

    # The simulator alone, and the two parts of an iteration, on the same members and batch.
    task = envs.task_at(family, 0)
    actions = 0.5 * jax.random.normal(jax.random.PRNGKey(1), (T, members * B, family.action_size))
    step = jax.vmap(family.step, (0, 0, None))

    @jax.jit
    def raw(rng, actions):
        state = jax.vmap(family.reset, (0, None))(jax.random.split(rng, members * B), task)
        _, rewards = jax.lax.scan(lambda s, a: (lambda n: (n, n.reward))(step(s, a, task)), state, actions)
        return rewards

    member_keys = jax.random.split(jax.random.PRNGKey(3), members)
    params = jax.vmap(lambda k: ppo.init_params(config.ppo, family, k))(member_keys)
    optimizer = ppo.make_optimizer(config.ppo)
    opt_state = jax.vmap(optimizer.init)(params)
    roll = jax.jit(jax.vmap(lambda p, k: acting.rollout(family, p.policy, task, k, B)))
    update = jax.jit(jax.vmap(lambda p, o, tr, k: ppo.ppo_update(config.ppo, optimizer, p, o, tr, k)[:3]))
    traj = jax.block_until_ready(roll(params, member_keys)) if parts else None

    cases = {"raw": (raw, (jax.random.PRNGKey(2), actions)), "program": (bound.learn_chunk, chunk_args)}
    if parts:
        cases.update(rollout=(roll, (params, member_keys)), update=(update, (params, opt_state, traj, member_keys)))
    first = {name: _seconds(fn, *args)[0] for name, (fn, args) in cases.items()}
    if compile_only:
        return (f"family={family_name} method={method} members={members} compile_only=1 "
                + " ".join(f"{name}_first_call_s={s:.1f}" for name, s in first.items()))
    if signal:
        open(signal, "w").close()
    while wait_for and not os.path.exists(wait_for):
        time.sleep(0.5)
    times = {name: [] for name in cases}
    iterations = None
    for _ in range(repeats):  # taking turns, so that a drift of the machine's speed touches every case alike
        for name, (fn, args) in cases.items():
            seconds, out = _seconds(fn, *args)
            times[name].append(seconds)
            if name == "program":
                iterations = int(np.sum(np.asarray(out[1].task.iterations)))
    best = {name: min(t) for name, t in times.items()}
    raw_steps, program_steps = T * members * B, iterations * B * T
    ratio = float(np.median([(program_steps / p) / (raw_steps / r) for p, r in zip(times["program"], times["raw"])]))
    per_member_its = iterations / members
    text = (f"family={family_name} method={method} backend={jax.default_backend()} members={members} "
            f"batch={members * B} tasks={tasks} budget={budget} iterations={iterations} "
            f"num_updates={config.ppo.num_updates} raw_steps_per_s={raw_steps / best['raw']:.0f} "
            f"program_steps_per_s={program_steps / best['program']:.0f} "
            f"iteration_s={best['program'] / per_member_its:.3f} raw_compile_s={first['raw']:.1f} "
            f"program_compile_s={first['program']:.1f} ")
    if parts:
        other = (best["program"] - per_member_its * (best["rollout"] + best["update"])) / tasks
        text += (f"rollout_s={best['rollout']:.3f} update_s={best['update']:.3f} other_s_per_task={other:.3f} "
                 f"rollout_share={per_member_its * best['rollout'] / best['program']:.3f} "
                 f"update_share={per_member_its * best['update'] / best['program']:.3f} ")
    return text + f"ratio={ratio:.3f}"


def main():
    from jcomps.runner import compile_cache

    compile_cache.from_environment()  # a second run of the benchmark loads its programs
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--family", default="cheetah_vel")
    parser.add_argument("--method", default="comps")
    parser.add_argument("--members", nargs="+", type=int, default=[1, 4])
    parser.add_argument("--tasks", type=int, default=2)
    parser.add_argument("--budget", type=int, default=40,
                        help="iterations per task at most (a task also ends at the success threshold, as in a run)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-parts", dest="parts", action="store_false",
                        help="time the program and raw stepping only (two compilations fewer)")
    parser.add_argument("--compile-only", action="store_true", help="compile and run each case once, then stop")
    parser.add_argument("--wait-for", default=None, metavar="FILE",
                        help="after compiling, wait until FILE exists before timing (compile while other jobs run, "
                             "time alone; the chunk program holds host callbacks, which JAX's persistent "
                             "compilation cache does not keep)")
    parser.add_argument("--signal", default=None, metavar="FILE",
                        help="create FILE once compiled (before --wait-for), so that a script running several "
                             "benchmarks side by side can time them one at a time")
    args = parser.parse_args()
    hostdevices.configure(1)
    import jax

    print(f"backend={jax.default_backend()} devices={jax.devices()}", flush=True)
    for m in args.members:
        print(bench(args.family, args.method, m, args.tasks, args.budget, args.repeats, args.parts,
                    args.compile_only, args.wait_for, args.signal), flush=True)


if __name__ == "__main__":
    main()
