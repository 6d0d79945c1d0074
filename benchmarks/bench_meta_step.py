"""Time of one jitted CoMPS meta step (second order) on CPU, at paper sizes, with 1, 10 and 40 stored tasks.

Ant sizes: obs 27, action 8, policy [128, 64]; per task 2,000 inner samples (10 trajectories of 200 steps from D_j)
and 2,000 skilled samples (10 trajectories from D*_j), or as many as ``--inner-trajectories`` and
``--skilled-trajectories`` ask (100 and 20: every trajectory the stores hold, a full batch). One meta step =
sampling both batches for every task, the inner policy-gradient step per task, the behaviour-cloning outer gradient
through it, the value-head gradient and both Adam updates. ``ratio_to_bc`` compares it with one plain BC gradient
step (plus Adam) on the same skilled data. One line per case as ``key=value`` pairs.

    python benchmarks/bench_meta_step.py [--tasks 1 10 40] [--repeats 10] [--first-order] [--task-chunk 0] \
        [--inner-trajectories 10 100] [--skilled-trajectories 10]
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jcomps.training import buffers, meta, networks
from jcomps.training.acting import Trajectory

OBS, ACT, T, HIDDEN = 27, 8, 200, (128, 64)


def _stores(num_tasks: int, seed: int = 0) -> buffers.SequenceStores:
    rng = np.random.default_rng(seed)
    f = lambda *s: jnp.asarray(rng.normal(size=s).astype(np.float32))  # noqa: E731
    ones = lambda *s: jnp.ones(s, jnp.float32)  # noqa: E731
    traj = Trajectory(f(num_tasks, T, 100, OBS), f(num_tasks, T, 100, ACT), f(num_tasks, T, 100) - 5.0,
                      f(num_tasks, T, 100), jnp.zeros((num_tasks, T, 100)), ones(num_tasks, T, 100),
                      jnp.zeros((num_tasks, T, 100)), f(num_tasks, 100, OBS))
    skilled = buffers.SkilledStore(f(num_tasks, T, 20, OBS), f(num_tasks, T, 20, ACT), ones(num_tasks, T, 20),
                                   f(num_tasks, 20))
    return buffers.SequenceStores(skilled, buffers.OffPolicyStore(traj, ones(num_tasks, 100)),
                                  jnp.ones((num_tasks,), bool))


def _best(fn, args, repeats):
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return compile_s, min(times)


def bench(num_tasks: int, repeats: int, first_order: bool, chunk: int = 0, inner: int = 10, skilled: int = 10) -> str:
    config = meta.MetaConfig(num_meta_steps=1, num_outer_steps=1, inner_trajectories=inner,
                             skilled_trajectories=skilled, first_order=first_order, task_chunk=chunk)
    stores = _stores(num_tasks)
    policy = networks.init_actor_critic(jax.random.PRNGKey(0), OBS, ACT, HIDDEN, 0.5).policy
    value = meta.init_value_heads(jax.random.PRNGKey(1), OBS, HIDDEN, num_tasks)
    p_opt, v_opt = meta.optimizers(config)
    state = meta.MetaState(policy, value, p_opt.init(policy), v_opt.init(value))

    step = jax.jit(lambda s, st, r: meta.meta_train(config, s, st, r)[0])
    meta_compile, meta_s = _best(step, (state, stores, jax.random.PRNGKey(2)), repeats)

    batches = meta.sample_batches(config, stores, jax.random.PRNGKey(2))
    adam = optax.adam(config.outer_learning_rate)

    @jax.jit
    def bc_step(policy, opt_state, b):
        loss = lambda p: meta.bc_loss(p, b.skilled_obs, b.skilled_action, b.skilled_valid)  # noqa: E731
        updates, opt_state = adam.update(jax.grad(loss)(policy), opt_state, policy)
        return optax.apply_updates(policy, updates), opt_state

    _, bc_s = _best(bc_step, (policy, adam.init(policy), batches), repeats)
    samples = num_tasks * (inner * T + skilled * T)
    return (f"tasks={num_tasks} inner_trajectories={inner} skilled_trajectories={skilled} "
            f"order={'first' if first_order else 'second'} "
            f"task_chunk={meta.task_chunk(config, num_tasks)} compile_s={meta_compile:.1f} "
            f"step_s={meta_s:.4f} samples_per_s={samples / meta_s:.0f} bc_step_s={bc_s:.4f} "
            f"ratio_to_bc={meta_s / bc_s:.2f}")


def main():
    from jcomps.runner import compile_cache

    compile_cache.from_environment()  # a second run of the benchmark loads its programs
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", nargs="+", type=int, default=[1, 10, 40])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--first-order", action="store_true")
    parser.add_argument("--task-chunk", nargs="+", type=int, default=[0],
                        help="slots per loop iteration of the meta step (0: by backend, 1 on CPU, 8 elsewhere)")
    parser.add_argument("--inner-trajectories", nargs="+", type=int, default=[10],
                        help="trajectories of D_j per inner step (the stores hold 100 per task)")
    parser.add_argument("--skilled-trajectories", nargs="+", type=int, default=[10],
                        help="trajectories of D*_j per outer step (the stores hold 20 per task)")
    args = parser.parse_args()
    print(f"backend={jax.default_backend()} devices={jax.device_count()}", flush=True)
    for chunk in args.task_chunk:
        for n in args.tasks:
            for inner in args.inner_trajectories:
                for skilled in args.skilled_trajectories:
                    print(bench(n, args.repeats, args.first_order, chunk, inner, skilled), flush=True)


if __name__ == "__main__":
    main()
