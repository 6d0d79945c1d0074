"""Experience stores of CoMPS as fixed-size pytrees (paper §4 and appendix "RL Training Details").

For each task i of a sequence:

- D*_i, the *skilled* store: the ``num_skilled`` (20) highest-return trajectories seen by the RL step on task i,
  kept incrementally as iterations arrive (top-k merge), never by storing everything.
- D_i, the *off-policy* store: ``num_offpolicy`` (100) trajectories sampled from the last
  k = min(M, ⌈0.05·N⌉) iterations (M iterations used, N the budget), with the behaviour policy's
  log-probabilities. While the task runs, a ring of the last ⌈0.05·N⌉ iterations holds the candidates.

``SequenceStores`` holds both for every task slot of a sequence, with validity masks, so a meta step can cover
tasks j ≤ i inside ``lax.scan`` without recompiling. Trajectories are time-major: ``[T, K, ...]`` per slot.

Every store is built from an example of the trajectories it will hold (as flashbax's ``init(experience)``): a
``Trajectory`` of arrays or of ``jax.ShapeDtypeStruct`` (``rollout_example``: a rollout's, from the family's
sizes), whose shapes and dtypes give T, the batch size, the observation and action sizes; the ``*_init_like``
functions take it and the capacities only. The sized ``*_init`` functions build the same stores
from an example of float32 trajectories of the sizes given (``trajectory_spec``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jcomps.training.acting import Trajectory


class SkilledStore(NamedTuple):
    """The top-K trajectories by undiscounted return.

    Attributes:
      obs: f32[T, K, obs_size]; action: f32[T, K, A]; valid: f32[T, K] (0 after a termination).
      returns: f32[K], −inf in empty rows.
    """

    obs: jax.Array
    action: jax.Array
    valid: jax.Array
    returns: jax.Array


class RecentStore(NamedTuple):
    """A ring of the last ``capacity`` iterations' batches: ``traj`` fields have a leading [capacity] axis.

    ``finite`` (bool[capacity, B]) marks the trajectories free of NaN and infinity (only those are sampled);
    ``iterations`` (i32[]) counts the batches ever added.
    """

    traj: Trajectory
    finite: jax.Array
    iterations: jax.Array


class OffPolicyStore(NamedTuple):
    """Sampled trajectories with behaviour log-probabilities: ``traj`` fields [T, N, ...], ``mask`` f32[N]."""

    traj: Trajectory
    mask: jax.Array


class SequenceStores(NamedTuple):
    """D* and D for every task slot of a sequence; leaves have a leading [num_slots] axis.

    ``task_valid`` (bool[num_slots]) marks slots whose task has been learnt.
    """

    skilled: SkilledStore
    offpolicy: OffPolicyStore
    task_valid: jax.Array


def recent_capacity(budget: int, fraction: float = 0.05) -> int:
    """⌈fraction·N⌉ iterations, the most D_i is sampled from."""
    return max(1, math.ceil(fraction * budget))


def trajectory_spec(T: int, B: int, obs_size: int, action_size: int) -> Trajectory:
    """The shapes of a batch of B float32 trajectories of T steps (``jax.ShapeDtypeStruct`` leaves, as every
    rollout's): an example to build stores from when there is no rollout to trace."""
    f = lambda *s: jax.ShapeDtypeStruct(s, jnp.float32)  # noqa: E731
    return Trajectory(f(T, B, obs_size), f(T, B, action_size), f(T, B), f(T, B), f(T, B), f(T, B), f(T, B),
                      f(B, obs_size))


def rollout_example(family, num_envs: int) -> Trajectory:
    """The shapes and dtypes of a batch ``acting.rollout`` returns for ``family`` and ``num_envs`` episodes (any
    policy, task or actor: float32, [T_max, num_envs, ...]), as ``jax.ShapeDtypeStruct`` leaves: the example a store
    of such batches is built from. From the family's sizes, not by tracing a rollout (``jax.eval_shape`` of one
    costs about 2 s of tracing on Half-Cheetah, in every program that builds a store); a test checks it against a
    real rollout."""
    return trajectory_spec(family.max_steps, num_envs, family.obs_size, family.action_size)


def _empty_traj(example: Trajectory, B: int, lead=()) -> Trajectory:
    """Zeros of ``example``'s dtypes and shapes with its batch axis set to ``B`` ([T, B, ...] per step,
    last_obs [B, ...]) and ``lead`` axes in front."""
    z = lambda x, *s: jnp.zeros(lead + s, x.dtype)  # noqa: E731
    per_step = jax.tree.map(lambda x: z(x, x.shape[0], B, *x.shape[2:]), example._replace(last_obs=None))
    return per_step._replace(last_obs=z(example.last_obs, B, *example.last_obs.shape[1:]))


def skilled_init_like(example: Trajectory, num_skilled: int) -> SkilledStore:
    """An empty skilled store of ``num_skilled`` trajectories shaped as ``example``'s ([T, B, ...]; any B)."""
    empty = _empty_traj(example, num_skilled)
    return SkilledStore(empty.obs, empty.action, empty.valid,
                        jnp.full((num_skilled,), -jnp.inf, example.reward.dtype))


def skilled_init(T: int, num_skilled: int, obs_size: int, action_size: int) -> SkilledStore:
    """An empty skilled store, sized by hand (``skilled_init_like`` of a float32 ``trajectory_spec``)."""
    return skilled_init_like(trajectory_spec(T, 1, obs_size, action_size), num_skilled)


def finite_trajectories(traj: Trajectory) -> jax.Array:
    """bool[B]: the trajectories of ``traj`` ([T, B, ...]) whose every field is free of NaN and infinity."""
    per_step = traj._replace(last_obs=None)
    ok = [jnp.all(jnp.isfinite(x).reshape(x.shape[:2] + (-1,)), axis=(0, 2)) for x in jax.tree.leaves(per_step)]
    ok.append(jnp.all(jnp.isfinite(traj.last_obs), axis=-1))
    return jnp.all(jnp.stack(ok), axis=0)


def _zero_nonfinite(traj: Trajectory, ok: jax.Array) -> Trajectory:
    """``traj`` with every value of the trajectories not ``ok`` (bool[B]) replaced by 0, so that no NaN is
    stored, not even in a row that is never sampled (0 · NaN would still be NaN)."""
    def zero(x, batch_axis):
        keep = jnp.expand_dims(ok, tuple(a for a in range(x.ndim) if a != batch_axis))
        return jnp.where(keep, x, jnp.zeros_like(x))

    per_step = jax.tree.map(lambda x: zero(x, 1), traj._replace(last_obs=None))
    return per_step._replace(last_obs=zero(traj.last_obs, 0))


def skilled_update(store: SkilledStore, traj: Trajectory) -> SkilledStore:
    """Merges a batch ``traj`` ([T, B, ...]) into the store, keeping the K highest returns. Trajectories holding
    NaN or infinity never enter (return −inf, data zeroed)."""
    k = store.returns.shape[0]
    ok = finite_trajectories(traj)
    traj = _zero_nonfinite(traj, ok)
    returns = jnp.concatenate([store.returns, jnp.where(ok, jnp.sum(traj.reward, axis=0), -jnp.inf)])
    top, idx = jax.lax.top_k(returns, k)
    pick = lambda old, new: jnp.take(jnp.concatenate([old, new], axis=1), idx, axis=1)  # noqa: E731
    return SkilledStore(pick(store.obs, traj.obs), pick(store.action, traj.action), pick(store.valid, traj.valid),
                        top)


def recent_init_like(example: Trajectory, capacity: int) -> RecentStore:
    """An empty ring of ``capacity`` iterations of batches shaped as ``example`` (one iteration's batch,
    [T, B, ...])."""
    B = example.reward.shape[1]
    return RecentStore(_empty_traj(example, B, (capacity,)), jnp.zeros((capacity, B), bool), jnp.int32(0))


def recent_init(capacity: int, T: int, B: int, obs_size: int, action_size: int) -> RecentStore:
    """An empty ring of ``capacity`` iterations of B trajectories, sized by hand (``recent_init_like``)."""
    return recent_init_like(trajectory_spec(T, B, obs_size, action_size), capacity)


def recent_add(store: RecentStore, traj: Trajectory) -> RecentStore:
    """Adds one iteration's batch, overwriting the oldest when full. Trajectories holding NaN or infinity are
    stored as zeros and marked not ``finite``: ``sample_offpolicy`` never picks them."""
    capacity = store.traj.reward.shape[0]
    slot = store.iterations % capacity
    ok = finite_trajectories(traj)
    put = lambda buf, x: jax.lax.dynamic_update_index_in_dim(buf, x, slot, 0)  # noqa: E731
    new = jax.tree.map(put, store.traj, _zero_nonfinite(traj, ok))
    return RecentStore(new, put(store.finite, ok), store.iterations + 1)


def pick_rows(rng: jax.Array, ok: jax.Array, num: int) -> tuple[jax.Array, jax.Array]:
    """``num`` indices into the rows of bool[n] ``ok``, drawn uniformly without replacement among the ok rows,
    and f32[num], 1 where the picked row is ok. Rows beyond the ok ones (or beyond n) are masked out."""
    n = ok.shape[0]
    keys = jnp.where(ok, jax.random.uniform(rng, (n,)), -1.0)
    score, idx = jax.lax.top_k(keys, min(num, n))
    if num > n:
        idx = jnp.concatenate([idx, jnp.zeros((num - n,), idx.dtype)])
        score = jnp.concatenate([score, jnp.full((num - n,), -1.0, score.dtype)])
    return idx, (score >= 0).astype(jnp.float32)


def sample_offpolicy(store: RecentStore, num: int, rng: jax.Array) -> OffPolicyStore:
    """``num`` trajectories drawn without replacement from the finite trajectories of every iteration in the ring
    (the last min(M, capacity) iterations); if fewer exist, the rest of the rows are masked out."""
    capacity, _, B = store.traj.reward.shape
    filled = jnp.minimum(store.iterations, capacity)
    candidate_ok = (jnp.arange(capacity) < filled)[:, None] & store.finite
    flat_idx, picked = pick_rows(rng, candidate_ok.reshape(-1), num)
    it, b = flat_idx // B, flat_idx % B
    per_step = store.traj._replace(last_obs=None)
    # x[it, :, b] puts the sampled axis first ([num, T, ...]); move it behind time.
    traj = jax.tree.map(lambda x: jnp.moveaxis(x[it, :, b], 0, 1), per_step)
    traj = traj._replace(last_obs=store.traj.last_obs[it, b])
    return OffPolicyStore(traj, picked)


def sequence_init_like(example: Trajectory, num_slots: int, num_skilled: int,
                       num_offpolicy: int) -> SequenceStores:
    """Empty stores for a sequence of ``num_slots`` tasks: ``num_skilled`` and ``num_offpolicy`` trajectories per
    slot, shaped as ``example``'s ([T, B, ...]; any B)."""
    skilled = jax.tree.map(lambda x: jnp.broadcast_to(x, (num_slots,) + x.shape),
                           skilled_init_like(example, num_skilled))
    off = OffPolicyStore(_empty_traj(example, num_offpolicy, (num_slots,)),
                         jnp.zeros((num_slots, num_offpolicy), jnp.float32))
    return SequenceStores(skilled, off, jnp.zeros((num_slots,), bool))


def sequence_init(num_slots: int, T: int, num_skilled: int, num_offpolicy: int, obs_size: int,
                  action_size: int) -> SequenceStores:
    """Empty stores for a sequence of ``num_slots`` tasks, sized by hand (``sequence_init_like``)."""
    return sequence_init_like(trajectory_spec(T, 1, obs_size, action_size), num_slots, num_skilled, num_offpolicy)


def sequence_write(stores: SequenceStores, slot: jax.Array, skilled: SkilledStore,
                   offpolicy: OffPolicyStore) -> SequenceStores:
    """Writes task ``slot``'s D* and D and marks it valid."""
    put = lambda buf, x: jax.lax.dynamic_update_index_in_dim(buf, x, slot, 0)  # noqa: E731
    return SequenceStores(jax.tree.map(put, stores.skilled, skilled), jax.tree.map(put, stores.offpolicy, offpolicy),
                          stores.task_valid.at[slot].set(True))


def sequence_bytes(num_slots: int, T: int, num_skilled: int, num_offpolicy: int, obs_size: int,
                   action_size: int) -> int:
    """Bytes of ``SequenceStores`` at these sizes (float32 everywhere)."""
    shapes = jax.eval_shape(lambda: sequence_init(num_slots, T, num_skilled, num_offpolicy, obs_size, action_size))
    return sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(shapes))


class TransitionStore(NamedTuple):
    """A replay buffer per task slot (PEARL): a ring of ``capacity`` transitions for each of ``num_slots`` slots.

    Leaves have leading axes [num_slots, capacity]: ``obs``, ``next_obs`` f32[..., obs_size]; ``action``
    f32[..., A]; ``reward``, ``done`` (1 where the transition terminated the episode; reaching T_max is a
    truncation and keeps ``done`` 0, so its next observation bootstraps), ``valid`` (1 for a step taken by a live
    episode) f32[...]; ``count`` i32[num_slots], transitions ever written to each slot. A slot never receives
    another slot's data: writes and samples take the slot index.
    """

    obs: jax.Array
    action: jax.Array
    reward: jax.Array
    next_obs: jax.Array
    done: jax.Array
    valid: jax.Array
    count: jax.Array


def transitions_init_like(example: Trajectory, num_slots: int, capacity: int) -> TransitionStore:
    """Empty replay buffers: ``num_slots`` slots of ``capacity`` transitions of trajectories shaped as
    ``example``'s ([T, B, ...]; any T and B)."""
    z = lambda x: jnp.zeros((num_slots, capacity) + x.shape[2:], x.dtype)  # noqa: E731
    return TransitionStore(z(example.obs), z(example.action), z(example.reward), z(example.obs), z(example.done),
                           z(example.valid), jnp.zeros((num_slots,), jnp.int32))


def transitions_init(num_slots: int, capacity: int, obs_size: int, action_size: int) -> TransitionStore:
    """Empty replay buffers, sized by hand (``transitions_init_like`` of a float32 ``trajectory_spec``)."""
    return transitions_init_like(trajectory_spec(1, 1, obs_size, action_size), num_slots, capacity)


def transitions_of(traj: Trajectory) -> dict:
    """The T·B transitions of a batch ``traj`` ([T, B, ...]), flattened time-major: the next observation of step
    t is the observation at t + 1, and at T_max the observation reached (``last_obs``: a truncation)."""
    next_obs = jnp.concatenate([traj.obs[1:], traj.last_obs[None]], axis=0)
    flat = {"obs": traj.obs, "action": traj.action, "reward": traj.reward, "next_obs": next_obs, "done": traj.done,
            "valid": traj.valid}
    return jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), flat)


def finite_transitions(traj: Trajectory) -> dict:
    """``transitions_of(traj)`` with the trajectories holding NaN or infinity zeroed and marked not ``valid``."""
    ok = finite_trajectories(traj)
    flat = transitions_of(_zero_nonfinite(traj, ok))
    flat["valid"] = flat["valid"] * jnp.broadcast_to(ok, traj.valid.shape).reshape(-1)
    return flat


def transitions_add(store: TransitionStore, slot: jax.Array, traj: Trajectory) -> TransitionStore:
    """Writes the batch ``traj`` into slot ``slot``'s ring, overwriting its oldest transitions when full (a batch
    larger than the ring keeps its last ``capacity`` transitions). Transitions holding NaN or infinity are stored
    as zeros with ``valid`` 0 (never sampled)."""
    flat = finite_transitions(traj)
    n = flat["reward"].shape[0]
    capacity = store.reward.shape[1]
    keep = min(n, capacity)  # of a batch larger than the ring, the last ``capacity`` rows survive
    flat = jax.tree.map(lambda x: x[n - keep:], flat)
    idx = (store.count[slot] + (n - keep) + jnp.arange(keep)) % capacity
    fields = {k: getattr(store, k).at[slot, idx].set(v.astype(getattr(store, k).dtype)) for k, v in flat.items()}
    return TransitionStore(**fields, count=store.count.at[slot].add(n))


def transitions_clear(store: TransitionStore, slot: jax.Array) -> TransitionStore:
    """Slot ``slot`` emptied (its count set to 0; the rows are overwritten by the next writes and never sampled
    before: ``transitions_sample`` draws from the first ``count`` rows)."""
    return store._replace(count=store.count.at[slot].set(0))


def transition_capacity(size: int, batch: int) -> int:
    """The ring size for a requested ``size``: whole batches of ``batch`` transitions, at least one."""
    return max(1, size // batch) * batch


def transitions_sample(store: TransitionStore, slot: jax.Array, num: int, rng: jax.Array,
                       valid_only: bool = False) -> tuple[dict, jax.Array]:
    """``num`` transitions of slot ``slot`` drawn uniformly (with replacement) from those written and still held,
    and f32[num], 1 where the row is a valid transition (0 for an empty slot or a step after a termination).

    With ``valid_only`` the draw is uniform over the held rows that are valid transitions (as a buffer that stores
    only the steps taken, oyster's, samples), so every row is one unless the slot holds none; for families whose
    episodes never end early every held row is valid (rows of non-finite episodes aside), and the cheaper uniform
    index of the default draws the same distribution."""
    capacity = store.reward.shape[1]
    held = jnp.minimum(store.count[slot], capacity)
    if valid_only:
        weight = store.valid[slot] * (jnp.arange(capacity) < held)
        cdf = jnp.cumsum(weight)
        u = jax.random.uniform(rng, (num,)) * cdf[-1]
        idx = jnp.minimum(jnp.searchsorted(cdf, u, side="right"), capacity - 1)
    else:
        idx = jax.random.randint(rng, (num,), 0, jnp.maximum(held, 1))
    rows = {k: getattr(store, k)[slot, idx] for k in ("obs", "action", "reward", "next_obs", "done", "valid")}
    mask = rows.pop("valid") * (held > 0).astype(jnp.float32)
    return rows, mask
