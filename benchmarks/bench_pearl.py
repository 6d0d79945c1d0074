"""What one PEARL iteration costs: collection plus gradient steps, against raw vmapped ``env.step`` for the same env
steps.

One iteration of ``pearl.learn_task`` with the family's default config (oyster's settings; budget 1, no initial
prior-z collection, from a state whose replay buffer already holds one batch, so the gradient steps sample real
data): ``num_trajectories`` episodes of T_max steps with the tanh-Gaussian policy (the prior-z share, then the
posterior's), the writes to the buffers, and ``num_updates`` gradient steps (critics, encoder, actor, Polyak;
``default``: the family's ratio of gradient steps to env steps), against ``num_trajectories`` · T_max raw steps with
precomputed actions in one jitted scan. The rollout alone (PEARL's policy) is timed too, so the gradient steps' share is
visible. One line per case, ``key=value`` pairs ending in ``ratio=<PEARL iteration throughput / raw throughput>``
(median over alternating timed pairs).

    python benchmarks/bench_pearl.py [--families cheetah_vel] [--num-updates 64 default] [--repeats 5]
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import numpy as np
from bench_rollout import make_raw, seconds  # the same raw baseline and timer (this folder is on sys.path)

from jcomps import envs, methods
from jcomps.training import acting


def bench(name: str, num_updates, repeats: int) -> str:
    family = envs.make(name)
    task = envs.task_at(family, 0)
    config = dataclasses.replace(methods.default_config("pearl", family), budget=1, num_updates=num_updates,
                                 max_tasks=2, initial_steps=0)
    method = methods.make("pearl", family, config)
    batch = config.num_trajectories
    steps = family.max_steps * batch
    learn = jax.jit(method.learn_task)
    state = method.init(jax.random.PRNGKey(0))
    start = time.perf_counter()
    state, _ = jax.block_until_ready(learn(state, task))  # now the buffer holds one batch: the timed iterations
    compile_s = time.perf_counter() - start  # sample real transitions (compile and one iteration)
    state = state._replace(task_index=jax.numpy.int32(0))
    actions = 0.5 * jax.random.normal(jax.random.PRNGKey(1), (family.max_steps, batch, family.action_size))

    raw = make_raw(family, task, batch)

    @jax.jit
    def rollout(rng, policy):
        return acting.rollout(family, policy, task, rng, batch, act=method.act).reward

    iteration = lambda s: learn(s, task)[1].iterations  # noqa: E731
    rng = jax.random.PRNGKey(2)
    policy = state.params.policy
    seconds(raw, (rng, actions))
    seconds(rollout, (rng, policy))
    t_it, t_raw, t_roll = [], [], []
    for _ in range(repeats):
        t_it.append(seconds(iteration, (state,)))
        t_raw.append(seconds(raw, (rng, actions)))
        t_roll.append(seconds(rollout, (rng, policy)))
    t_it, t_raw, t_roll = map(np.asarray, (t_it, t_raw, t_roll))
    ratio = float(np.median(t_raw / t_it))
    it_s, raw_s, roll_s = float(np.median(t_it)), float(np.median(t_raw)), float(np.median(t_roll))
    return (f"family={name} method=pearl num_updates={config.updates_for(family)} meta_batch={config.meta_batch} "
            f"minibatch={config.minibatch_size} steps={steps} raw_steps_per_s={steps / raw_s:.0f} "
            f"pearl_steps_per_s={steps / it_s:.0f} iteration_s={it_s:.3f} rollout_s={roll_s:.3f} "
            f"update_s={max(it_s - roll_s, 0.0):.3f} update_share={max(it_s - roll_s, 0.0) / it_s:.3f} "
            f"compile_s={compile_s:.1f} ratio={ratio:.3f}")


def main():
    from jcomps.runner import compile_cache

    compile_cache.from_environment()  # a second run of the benchmark loads its programs
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--families", nargs="+", default=["cheetah_vel"], choices=envs.FAMILIES)
    parser.add_argument("--num-updates", nargs="+", type=lambda v: None if v == "default" else int(v),
                        default=[64, None], help="gradient steps per iteration; 'default': the family's ratio")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    print(f"backend={jax.default_backend()} devices={jax.device_count()}", flush=True)
    for name in args.families:
        for n in args.num_updates:
            print(bench(name, n, args.repeats), flush=True)


if __name__ == "__main__":
    main()
