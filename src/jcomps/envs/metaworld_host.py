"""The host side of the MetaWorld family: the real ``metaworld`` package, stepped as pure functions.

MJX cannot load MetaWorld's scenes, so its tasks run in MuJoCo's C library on the host. To keep the family a
pure function of explicit inputs, like every other family, the whole simulator state travels with the JAX
state instead of living in a host object:

- ``reset(env, variant)`` gives the initial state of goal variant ``variant`` of environment ``env``
  (MetaWorld's resets of a frozen variant are deterministic);
- ``step(env, variant, state, action)`` loads ``state`` into a MetaWorld env of that variant, calls its own
  ``step`` (its reward, success and observation code, unchanged) and reads the new state back.

A state is MuJoCo's ``mjSTATE_INTEGRATION`` (everything ``mj_step`` reads: positions, velocities, mocap,
controls, solver warm start; enough for bit-exact continuation) followed by MetaWorld's ``_prev_obs`` (the
frame-stacked half of the observation), in float64, zero-padded to ``STATE_SIZE``. The JAX side carries it as
uint32 pairs (float64 bits), so nothing is rounded. One env object per (environment, variant) is kept (its
Python attributes, such as the goal and the reward's normalisers, are fixed by the variant), so a step is
``mj_setState`` + MetaWorld's step + ``mj_getState``.

``rollout(kind, policies, group, episode, env, variant, noise)`` runs whole episodes here, T_max steps, with
the policy evaluated by its NumPy twin (``jcomps.envs.host_acting``): the family's ``host_rollout``, one round trip
per rollout instead of one per step.

``Pool`` spreads a batch of steps or of episodes over worker processes, so stepping uses every core; being pure,
the result does not depend on how the batch is split. This module imports no JAX: the workers stay light.
"""

from __future__ import annotations

import collections
import functools
import os
import socket
import subprocess
import sys
import threading
import warnings
from multiprocessing.connection import Connection
from typing import Optional

import numpy as np

ENV_NAMES = ("push-wall-v3", "button-press-wall-v3", "hammer-v3")
"""The paper's three environments (it used their v2 versions; metaworld 3.1.1 has v3 only)."""
LETTERS = "PBH"
"""The paper's short names: Push-Wall (P), Button-Press-Wall (B), Hammer (H)."""
REWARD_VERSIONS = ("v2", "v1")
"""MetaWorld's reward functions (``reward_function_version``): "v2", the environments' default and the reward of
the v2 environments the paper used, and "v1", MetaWorld v1's original reward. A host environment index ``e``
names environment ``ENV_NAMES[e % 3]`` with reward ``REWARD_VERSIONS[e // 3]``."""
NUM_ENVS = len(ENV_NAMES) * len(REWARD_VERSIONS)
"""Host environment indices: 0-2 the three environments with the v2 reward, 3-5 with the v1 reward."""
NUM_VARIANTS = 50
"""Goal variants per environment: ``metaworld.ML1(name, seed=BENCHMARK_SEED).train_tasks``."""
BENCHMARK_SEED = 0
"""The seed of the ML1 benchmarks whose train tasks are the goal variants (fixed, so goal index k is one goal)."""
OBS_SIZE = 39
ACTION_SIZE = 4
MAX_STEPS = 150
PREV_OBS_SIZE = 18
STATE_SIZE = 322
"""float64 entries of a state: the largest mjSTATE_INTEGRATION of the three (Hammer, 304) plus ``_prev_obs``."""
_SPEC = 0  # set on first use: mujoco.mjtState.mjSTATE_INTEGRATION
_CACHE_SIZE = 64
# One thread at a time in here: metaworld builds its tasks with NumPy's global random state, and an env object
# must not be stepped by two threads (JAX calls back from one thread per device).
_LOCK = threading.RLock()


def variants(env: int) -> tuple:
    """The ``NUM_VARIANTS`` goal variants of environment ``env`` as metaworld ``Task``s, goal hidden.

    They are ML1's train tasks (the goal is not in the observation: as in the other families, the task must be
    inferred from reward), built by the real package. Takes a few seconds, once per process and environment.
    """
    with _LOCK:
        return _variants_of(env)


@functools.cache
def _variants_of(env: int) -> tuple:
    import metaworld

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tasks = metaworld.ML1(ENV_NAMES[env], seed=BENCHMARK_SEED).train_tasks
    if len(tasks) != NUM_VARIANTS:
        raise RuntimeError(f"metaworld gave {len(tasks)} variants of {ENV_NAMES[env]}, expected {NUM_VARIANTS}")
    return tuple(tasks)


class _Variant:
    """A MetaWorld env frozen to one goal variant, with its initial state."""

    def __init__(self, env: int, variant: int):
        import mujoco
        from metaworld.env_dict import ALL_V3_ENVIRONMENTS

        global _SPEC
        _SPEC = int(mujoco.mjtState.mjSTATE_INTEGRATION)
        self.mujoco = mujoco
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            name, version = ENV_NAMES[env % len(ENV_NAMES)], REWARD_VERSIONS[env // len(ENV_NAMES)]
            self.env = ALL_V3_ENVIRONMENTS[name](reward_function_version=version)
            self.env.set_task(variants(env % len(ENV_NAMES))[variant])
            # Time limits are ours (T_max = 150, a truncation); MetaWorld's own counter must never stop a step.
            self.env.max_path_length = np.iinfo(np.int32).max
            obs, _ = self.env.reset()
        self.n = mujoco.mj_stateSize(self.env.model, _SPEC)
        if self.n + PREV_OBS_SIZE > STATE_SIZE:
            raise RuntimeError(f"{name}: state of {self.n + PREV_OBS_SIZE} floats > STATE_SIZE")
        self.initial = (self.read(), np.asarray(obs, np.float64))

    def read(self) -> np.ndarray:
        state = np.zeros(STATE_SIZE, np.float64)
        self.mujoco.mj_getState(self.env.model, self.env.data, state[:self.n], _SPEC)
        state[self.n:self.n + PREV_OBS_SIZE] = self.env._prev_obs
        return state

    def step(self, state: np.ndarray, action: np.ndarray):
        self.mujoco.mj_setState(self.env.model, self.env.data, state[:self.n], _SPEC)
        self.env._prev_obs = state[self.n:self.n + PREV_OBS_SIZE].copy()
        self.env.curr_path_length = 0
        obs, reward, _, _, info = self.env.step(action)
        return self.read(), obs, float(reward), float(info["success"])


_variants: collections.OrderedDict = collections.OrderedDict()


def _get(env: int, variant: int) -> _Variant:
    key = (int(env), int(variant))
    v = _variants.get(key)
    if v is None:
        if not (0 <= key[0] < NUM_ENVS and 0 <= key[1] < NUM_VARIANTS):
            raise ValueError(f"metaworld task (environment {key[0]}, goal index {key[1]}) does not exist; "
                             f"environments 0-{NUM_ENVS - 1} (3-5: the v1 reward), goal indices 0-{NUM_VARIANTS - 1}")
        v = _variants[key] = _Variant(*key)
        if len(_variants) > _CACHE_SIZE:
            _variants.popitem(last=False)
    else:
        _variants.move_to_end(key)
    return v


def reset(env, variant):
    """Initial (state f64[N, STATE_SIZE], obs f64[N, 39]) of each (environment, goal index) pair (1-D arrays)."""
    env, variant = np.asarray(env).reshape(-1), np.asarray(variant).reshape(-1)
    states = np.empty((env.size, STATE_SIZE), np.float64)
    obs = np.empty((env.size, OBS_SIZE), np.float64)
    with _LOCK:
        for i, (e, k) in enumerate(zip(env, variant)):
            states[i], obs[i] = _get(e, k).initial
    return states, obs


def step(env, variant, state, action):
    """One MetaWorld step of each of N environments: (state, obs f64[N, 39], reward f64[N], success f64[N])."""
    n = len(env)
    states = np.empty((n, STATE_SIZE), np.float64)
    obs = np.empty((n, OBS_SIZE), np.float64)
    reward = np.empty(n, np.float64)
    success = np.empty(n, np.float64)
    action = np.asarray(action, np.float32)
    state = np.require(state, np.float64, ["C", "W"])  # MuJoCo's setter insists on writeable; it only reads
    with _LOCK:
        for i in range(n):
            states[i], obs[i], reward[i], success[i] = _get(env[i], variant[i]).step(state[i], action[i])
    return states, obs, reward, success


def rollout(kind: str, policies: list, group, episode, env, variant, noise):
    """Whole episodes from reset: T = ``noise.shape[1]`` steps of each of N episodes, acting with the NumPy twin
    ``kind`` of the policy ``policies[group[i]]`` (``host_acting.plain`` containers) on episode i.

    ``episode`` i32[N] is each episode's index within its own rollout (PEARL's per-episode z); ``noise``
    f32[N, T, A] is the policy's standard-normal noise. Returns (obs f32[N, T + 1, 39] (the last is the
    observation after the last step), action f32[N, T, A] (before the clip to [-1, 1] that the env applies),
    log_prob f32[N, T], reward f32[N, T], success f32[N, T]).
    """
    from jcomps.envs import host_acting

    env, variant, group = (np.asarray(x).reshape(-1) for x in (env, variant, group))
    episode = np.asarray(episode).reshape(-1)
    noise = np.asarray(noise, np.float32)
    n, steps = noise.shape[:2]
    states, obs0 = reset(env, variant)
    obs = np.empty((n, steps + 1, OBS_SIZE), np.float32)
    obs[:, 0] = obs0
    action = np.empty((n, steps, ACTION_SIZE), np.float32)
    log_prob = np.empty((n, steps), np.float32)
    reward = np.empty((n, steps), np.float32)
    success = np.empty((n, steps), np.float32)
    rows = [(g, np.flatnonzero(group == g)) for g in np.unique(group)]
    with _LOCK:
        sims = [_get(e, k) for e, k in zip(env, variant)]
        for t in range(steps):
            for g, r in rows:
                action[r, t], log_prob[r, t] = host_acting.act(kind, policies[g], obs[r, t], noise[r, t], episode[r])
            clipped = np.clip(action[:, t], -1.0, 1.0)
            for i, sim in enumerate(sims):
                states[i], obs[i, t + 1], reward[i, t], success[i, t] = sim.step(states[i], clipped[i])
    return obs, action, log_prob, reward, success


_JOBS = {"reset": reset, "step": step, "rollout": rollout}


def _worker(conn) -> None:
    """A pool worker: runs the jobs it is sent, ``(name, args)``, until it is sent None or the caller goes away."""
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            return
        if message is None:
            return
        try:
            name, args = message
            conn.send(("ok", _JOBS[name](*args)))
        except Exception as e:  # noqa: BLE001 - reported to the caller, which raises it
            conn.send(("error", f"{type(e).__name__}: {e}"))


def default_workers() -> int:
    """Worker processes that step in parallel: ``JCOMPS_METAWORLD_WORKERS`` or the number of cores this process
    may use."""
    value = os.environ.get("JCOMPS_METAWORLD_WORKERS")
    if value is not None:
        if not value.isdigit() or int(value) < 1:
            raise ValueError(f"JCOMPS_METAWORLD_WORKERS must be an integer >= 1, got {value!r}")
        return int(value)
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


class Pool:
    """Steps batches of MetaWorld environments on ``workers`` worker processes.

    The batch is cut into contiguous parts, one per worker; the caller only sends and receives. (It used to step
    a part itself; in a process that has imported JAX, MetaWorld steps ran 5-10% slower than in a light one,
    which cost the 2-worker Push-Wall benchmark its last 10%; see docs/log.md, "MetaWorld on the host".) Workers run
    this file as a script (so they import neither JAX nor the caller's ``__main__``: multiprocessing's ``spawn`` would
    re-run an unguarded script) and talk over a socket pair; they start on the first batch that needs them and end when
    the caller closes the pool or exits. Thread-safe (one batch at a time).
    """

    def __init__(self, workers: Optional[int] = None):
        self.workers = default_workers() if workers is None else workers
        if isinstance(self.workers, bool) or not isinstance(self.workers, int) or self.workers < 1:
            raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
        self._conns: list = []
        self._procs: list = []
        self._lock = threading.Lock()

    def _start(self, count: int) -> None:
        while len(self._conns) < count:
            ours, theirs = socket.socketpair()
            # -P: the script's folder (jcomps/envs, which has a mujoco.py) must not shadow packages.
            proc = subprocess.Popen([sys.executable, "-P", os.path.abspath(__file__), str(theirs.fileno())],
                                    pass_fds=[theirs.fileno()], stdin=subprocess.DEVNULL)
            theirs.close()
            self._conns.append(Connection(ours.detach()))
            self._procs.append(proc)

    def reset(self, env, variant):
        """``reset`` of the whole batch, spread over the pool."""
        return self._run("reset", len(env), lambda cut: (env[cut], variant[cut]))

    def step(self, env, variant, state, action):
        """``step`` of the whole batch, spread over the pool."""
        return self._run("step", len(env), lambda cut: (env[cut], variant[cut], state[cut], action[cut]))

    def rollout(self, kind: str, policies: list, group, episode, env, variant, noise):
        """``rollout`` of the whole batch of episodes, spread over the pool (each worker gets only the policies
        of its own episodes)."""
        group = np.asarray(group)

        def share(cut):
            used = np.unique(group[cut])
            return (kind, [policies[g] for g in used], np.searchsorted(used, group[cut]), episode[cut], env[cut],
                    variant[cut], noise[cut])

        return self._run("rollout", len(env), share)

    def _run(self, name: str, n: int, share):
        """Job ``name`` on contiguous parts of a batch of ``n`` (``share(cut)`` gives a part's arguments), one part
        per worker process; the parts' results are concatenated."""
        parts = min(self.workers, n)
        with self._lock:
            self._start(parts)
            bounds = np.linspace(0, n, parts + 1).astype(int)
            for conn, i in zip(self._conns, range(parts)):
                conn.send((name, share(slice(bounds[i], bounds[i + 1]))))
            replies = []
            for conn in self._conns[:parts]:
                try:
                    replies.append(conn.recv())
                except (EOFError, OSError) as e:
                    replies.append(("died", f"a worker process died ({type(e).__name__})"))
            if any(kind == "died" for kind, _ in replies):
                self.close()  # the next job starts fresh workers
            for kind, value in replies:
                if kind != "ok":
                    raise RuntimeError(f"metaworld worker failed: {value}")
        return tuple(np.concatenate(parts_) for parts_ in zip(*(value for _, value in replies)))

    def close(self) -> None:
        for conn in self._conns:
            try:
                conn.send(None)
            except (BrokenPipeError, OSError):
                pass
        for conn in self._conns:
            conn.close()
        for proc in self._procs:
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()
        self._conns, self._procs = [], []


if __name__ == "__main__":
    _worker(Connection(int(sys.argv[1])))

