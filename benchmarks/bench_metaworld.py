"""MetaWorld: env steps/s of the family's rollout (policy included) against raw stepping of the same envs.

Raw stepping is MetaWorld's own ``env.step`` on the same goal variant in a tight Python loop, precomputed
random actions, no JAX: what the simulator and MetaWorld's reward code cost alone. Our rollout is
``acting.rollout`` (the jitted scan that every method uses: Gaussian policy, ``pure_callback`` per batched step,
the pure host step that loads and reads MuJoCo's state) on ``workers`` processes. Each ``workers`` case is
compared with raw stepping on as many processes, each stepping its share of the batch (started together after
their set-up, timed by the slowest), so ``ratio`` is our cost against the simulator's at equal parallelism (goal
>= 0.9). Per batched step of the fastest rollout, ``host_step_ms`` is the time inside the host step (the callback:
MetaWorld's step, our state load and read, the pool's round trip and lockstep wait) and ``outside_ms`` the rest
(the policy, the scan, the callback's dispatch), against ``raw_ms_per_step``. One ``key=value`` line per case::

    python benchmarks/bench_metaworld.py [--envs 0 1 2] [--batch 20] [--workers 1 2] [--repeats 5]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
import warnings

import numpy as np


def raw_loop(env: int, variant: int, batch: int, seed: int) -> float:
    """Seconds for ``batch`` MetaWorld envs of one variant to step one episode (150 steps) each, after reset."""
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    from jcomps.envs import metaworld_host as host

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        envs = [ALL_V3_ENVIRONMENTS[host.ENV_NAMES[env]]() for _ in range(batch)]
        for e in envs:
            e.set_task(host.variants(env)[variant])
            e.max_path_length = host.MAX_STEPS
            e.reset()
    actions = np.random.default_rng(seed).uniform(-1, 1, (host.MAX_STEPS, batch, host.ACTION_SIZE))
    actions = actions.astype(np.float32)
    start = time.perf_counter()
    for t in range(host.MAX_STEPS):
        for i, e in enumerate(envs):
            e.step(actions[t, i])
    return time.perf_counter() - start


def raw_parallel(env: int, variant: int, batch: int, workers: int) -> float:
    """Wall seconds of ``raw_loop`` split over ``workers`` processes started together (the slowest counts)."""
    shares = np.diff(np.linspace(0, batch, workers + 1).astype(int))
    procs = [subprocess.Popen([sys.executable, __file__, "--raw-worker", str(env), str(variant), str(n), str(i)],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
             for i, n in enumerate(shares)]
    for p in procs:  # each says "ready" after its set-up, then all start at once
        assert p.stdout.readline().strip() == "ready"
    for p in procs:
        p.stdin.write("go\n")
        p.stdin.flush()
    return max(float(p.communicate()[0].strip()) for p in procs)


def _raw_worker(env: int, variant: int, batch: int, seed: int) -> None:
    raw_loop(env, variant, 1, seed)  # imports and variant set-up before the start signal
    print("ready", flush=True)
    sys.stdin.readline()
    print(raw_loop(env, variant, batch, seed), flush=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", type=int, default=[0, 1, 2], help="0 Push-Wall, 1 Button, 2 Hammer")
    parser.add_argument("--batch", type=int, default=20, help="episodes per rollout (our methods' iteration)")
    parser.add_argument("--workers", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()

    import jax

    from jcomps import acting, envs, ppo
    from jcomps.envs import metaworld as mw
    from jcomps.envs import metaworld_host as host

    # Time spent inside the host step (the callback), so each line splits our cost into the host step and what
    # runs outside it (the policy, the scan, the callback's dispatch). Wrapped before any rollout is traced.
    inside = [0.0]
    host_step = mw._host_step

    def timed_host_step(*a):
        start = time.perf_counter()
        out = host_step(*a)
        inside[0] += time.perf_counter() - start
        return out

    mw._host_step = timed_host_step
    family = envs.make("metaworld")
    policy = ppo.init_params(ppo.family_config("metaworld"), family, jax.random.PRNGKey(0)).policy
    steps = args.batch * host.MAX_STEPS
    print(f"backend={jax.default_backend()} cores={host.default_workers()}", flush=True)
    for env in args.envs:
        task = family.tasks([mw.code(env, env)])
        task = jax.tree.map(lambda x: x[0], task)
        rollout = jax.jit(lambda rng: acting.rollout(family, policy, task, rng, args.batch).reward)
        for workers in args.workers:
            os.environ["JCOMPS_METAWORLD_WORKERS"] = str(workers)
            mw.pool().close()
            mw.pool.cache_clear()
            start = time.perf_counter()
            jax.block_until_ready(rollout(jax.random.PRNGKey(0)))  # compile, worker start, variant set-up
            first = time.perf_counter() - start
            ours, raw, host_s = [], [], []
            for r in range(args.repeats):  # alternate, so both see the same machine load
                inside[0] = 0.0
                start = time.perf_counter()
                jax.block_until_ready(rollout(jax.random.PRNGKey(r + 1)))
                ours.append(time.perf_counter() - start)
                host_s.append(inside[0])
                raw.append(raw_loop(env, env, args.batch, r) if workers == 1
                           else raw_parallel(env, env, args.batch, workers))
            ratio = float(np.median(np.asarray(raw) / np.asarray(ours)))
            best = int(np.argmin(ours))  # per batched step, in the fastest rollout
            host_ms, outside_ms = (1e3 * host_s[best] / host.MAX_STEPS,
                                   1e3 * (ours[best] - host_s[best]) / host.MAX_STEPS)
            print(f"env={host.ENV_NAMES[env]} batch={args.batch} workers={workers} steps={steps} "
                  f"raw_steps_per_s={steps / min(raw):.0f} rollout_steps_per_s={steps / min(ours):.0f} "
                  f"raw_ms_per_step={1e3 * min(raw) / host.MAX_STEPS:.3f} host_step_ms={host_ms:.3f} "
                  f"outside_ms={outside_ms:.3f} first_call_s={first:.1f} ratio={ratio:.3f}", flush=True)
    mw.pool().close()


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--raw-worker":
        _raw_worker(*map(int, sys.argv[2:6]))
    else:
        main()
