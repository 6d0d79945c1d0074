"""MetaWorld: env steps/s of the family's rollout (policy included) against raw stepping of the same envs.

Raw stepping is MetaWorld's own ``env.step`` in a tight Python loop over ``batch`` envs of the same goal variant,
no JAX, replaying the very actions our rollout took (so both simulate the same motions: contact-rich motions cost
more): what the simulator and MetaWorld's reward code cost alone. Our rollout is ``acting.rollout`` jitted, as
every method runs it, on ``workers`` processes (the caller's included):

- ``path=rollout``: the family's ``host_rollout``, whole episodes per worker with the policy's NumPy twin (what
  the methods use);
- ``path=step``: the per-step path (one ``pure_callback`` and one worker round trip per step, the policy in JAX),
  which an ``act`` without a twin falls back to.

Each ``workers`` case is compared with raw stepping on as many fresh processes, each replaying its share of the
batch (started together after their set-up, timed by the slowest), so ``ratio`` is our cost against the
simulator's at equal parallelism (goal >= 0.9). Fresh processes for raw stepping, because our workers are light
processes too: MetaWorld steps 5-10% slower in a process that has imported JAX (docs/log.md, "MetaWorld on the host").
One ``key=value`` line per case::

    python benchmarks/bench_metaworld.py [--envs 0 1 2] [--batch 20] [--workers 1 2] [--paths rollout step]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
import warnings

import numpy as np


def raw_loop(env: int, variant: int, actions: np.ndarray) -> float:
    """Seconds for ``B`` MetaWorld envs of one variant to step ``actions`` f32[T, B, A] after a reset."""
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    from jcomps.envs import metaworld_host as host

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        envs = [ALL_V3_ENVIRONMENTS[host.ENV_NAMES[env]]() for _ in range(actions.shape[1])]
        for e in envs:
            e.set_task(host.variants(env)[variant])
            e.max_path_length = actions.shape[0]
            e.reset()
    start = time.perf_counter()
    for t in range(actions.shape[0]):
        for i, e in enumerate(envs):
            e.step(actions[t, i])
    return time.perf_counter() - start


def raw_parallel(env: int, variant: int, actions: np.ndarray, workers: int) -> float:
    """Wall seconds of ``raw_loop`` split over ``workers`` processes started together (the slowest counts)."""
    bounds = np.linspace(0, actions.shape[1], workers + 1).astype(int)
    with tempfile.TemporaryDirectory() as tmp:
        paths = []
        for i in range(workers):
            paths.append(os.path.join(tmp, f"actions{i}.npy"))
            np.save(paths[-1], actions[:, bounds[i]:bounds[i + 1]])
        procs = [subprocess.Popen([sys.executable, __file__, "--raw-worker", str(env), str(variant), path],
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True) for path in paths]
        for p in procs:  # each says "ready" after its set-up, then all start at once
            assert p.stdout.readline().strip() == "ready"
        for p in procs:
            p.stdin.write("go\n")
            p.stdin.flush()
        return max(float(p.communicate()[0].strip()) for p in procs)


def _raw_worker(env: int, variant: int, path: str) -> None:
    actions = np.load(path)
    raw_loop(env, variant, actions[:2, :1])  # imports and variant set-up before the start signal
    print("ready", flush=True)
    sys.stdin.readline()
    print(raw_loop(env, variant, actions), flush=True)


def main():
    from jcomps.runner import compile_cache

    compile_cache.from_environment()  # a second run of the benchmark loads its programs
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", type=int, default=[0, 1, 2], help="0 Push-Wall, 1 Button, 2 Hammer")
    parser.add_argument("--batch", type=int, default=20, help="episodes per rollout (our methods' iteration)")
    parser.add_argument("--workers", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--paths", nargs="+", choices=["rollout", "step"], default=["rollout", "step"])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    import jax

    from jcomps import envs, methods
    from jcomps.envs import metaworld as mw
    from jcomps.envs import metaworld_host as host
    from jcomps.training import acting, ppo

    family = envs.make("metaworld")
    config = methods.default_config("ppo_tl", "metaworld").ppo
    policy = ppo.init_params(config, family, jax.random.PRNGKey(0)).policy
    steps = args.batch * host.MAX_STEPS
    print(f"backend={jax.default_backend()} cores={host.default_workers()}", flush=True)
    for env in args.envs:
        task = family.tasks([mw.code(env, env)])
        task = jax.tree.map(lambda x: x[0], task)
        for path in args.paths:
            # without its NumPy twin the Gaussian policy takes the per-step path
            actor = acting.GAUSSIAN if path == "rollout" else acting.Actor(acting.GAUSSIAN.act)
            rollout = jax.jit(lambda rng, a=actor: acting.rollout(family, policy, task, rng, args.batch, a).action)
            for workers in args.workers:
                os.environ["JCOMPS_METAWORLD_WORKERS"] = str(workers)
                mw.pool().close()
                mw.pool.cache_clear()
                start = time.perf_counter()
                jax.block_until_ready(rollout(jax.random.PRNGKey(0)))  # compile, worker start, variant set-up
                first = time.perf_counter() - start
                ours, raw = [], []
                for r in range(args.repeats):  # alternate, so both see the same machine load
                    start = time.perf_counter()
                    actions = np.asarray(jax.block_until_ready(rollout(jax.random.PRNGKey(r + 1))))
                    ours.append(time.perf_counter() - start)
                    raw.append(raw_parallel(env, env, actions, workers))
                ratio = float(np.median(np.asarray(raw) / np.asarray(ours)))
                print(f"env={host.ENV_NAMES[env]} path={path} batch={args.batch} workers={workers} steps={steps} "
                      f"raw_steps_per_s={steps / min(raw):.0f} rollout_steps_per_s={steps / min(ours):.0f} "
                      f"raw_ms_per_step={1e3 * min(raw) / host.MAX_STEPS:.3f} "
                      f"rollout_ms_per_step={1e3 * min(ours) / host.MAX_STEPS:.3f} first_call_s={first:.1f} "
                      f"ratio={ratio:.3f}", flush=True)
    mw.pool().close()


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--raw-worker":
        _raw_worker(int(sys.argv[2]), int(sys.argv[3]), sys.argv[4])
    else:
        main()
