"""Throughput of the PPO rollout (policy sampling included) against raw vmapped ``env.step``.

Both run T_max steps of B fresh episodes in one jitted ``lax.scan`` on the same family and batch; "raw"
feeds precomputed actions to ``family.step``, "rollout" is ``jcomps.training.acting.rollout`` with a [128, 64]
Gaussian policy. One line per case, ``key=value`` pairs ending in ``ratio=<rollout/raw>`` (throughput ratio,
the median over alternating timed pairs; ``best_ratio`` compares the best times instead).

    python benchmarks/bench_rollout.py [--families cheetah_vel ant_goal] [--batches 20 256] [--repeats 5]
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from jcomps import envs
from jcomps.training import acting, ppo


def seconds(fn, args):
    """Wall seconds of ``fn(*args)``, results ready."""
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - start


def _time_pair(a, a_args, b, b_args, repeats):
    """Compile times, best-of-``repeats`` run times of ``a`` and ``b``, and the median of the per-repeat time
    ratios a/b. The two are timed alternately, so each ratio compares runs made under the same machine load
    (on a shared 2-core machine throughput drifts by 30% within a minute)."""
    compile_a, compile_b = seconds(a, a_args), seconds(b, b_args)
    times_a, times_b = [], []
    for _ in range(repeats):
        times_a.append(seconds(a, a_args))
        times_b.append(seconds(b, b_args))
    ratio = float(np.median(np.asarray(times_a) / np.asarray(times_b)))
    return compile_a, min(times_a), compile_b, min(times_b), ratio


def bench(name: str, batch: int, repeats: int) -> str:
    family = envs.make(name)
    task = envs.task_at(family, 0)
    policy = ppo.init_params(ppo.PPOConfig(), family, jax.random.PRNGKey(0)).policy
    actions = 0.5 * jax.random.normal(jax.random.PRNGKey(1), (family.max_steps, batch, family.action_size))

    raw = make_raw(family, task, batch)

    @jax.jit
    def roll(rng, policy):
        return acting.rollout(family, policy, task, rng, batch).reward

    rng = jax.random.PRNGKey(2)
    raw_compile, raw_s, roll_compile, roll_s, ratio = _time_pair(raw, (rng, actions), roll, (rng, policy), repeats)
    steps = family.max_steps * batch
    return (f"family={name} batch={batch} steps={steps} raw_steps_per_s={steps / raw_s:.0f} "
            f"rollout_steps_per_s={steps / roll_s:.0f} raw_compile_s={raw_compile:.1f} "
            f"rollout_compile_s={roll_compile:.1f} best_ratio={raw_s / roll_s:.3f} ratio={ratio:.3f}")


def make_raw(family, task, batch: int):
    """``raw(rng, actions f32[T, batch, A]) -> rewards``: ``batch`` fresh episodes of ``task`` stepped with the
    precomputed ``actions`` by vmapped ``family.step`` in one jitted ``lax.scan``, no policy: the simulator alone
    (also the baseline of ``bench_pearl.py``)."""
    step = jax.vmap(family.step, (0, 0, None))

    def body(state, action):
        nxt = step(state, action, task)
        return nxt, nxt.reward

    @jax.jit
    def raw(rng, actions):
        state = jax.vmap(family.reset, (0, None))(jax.random.split(rng, batch), task)
        return jax.lax.scan(body, state, actions)[1]

    return raw


def main():
    from jcomps.runner import compile_cache

    compile_cache.from_environment()  # a second run of the benchmark loads its programs
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--families", nargs="+", default=["cheetah_vel", "ant_goal"], choices=envs.FAMILIES)
    parser.add_argument("--batches", nargs="+", type=int, default=[20, 256])
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args()
    print(f"backend={jax.default_backend()} devices={jax.device_count()}", flush=True)
    for name in args.families:
        for batch in args.batches:
            print(bench(name, batch, args.repeats), flush=True)


if __name__ == "__main__":
    main()
