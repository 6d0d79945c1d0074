"""Tests of the experience stores: the true top-K by return, sampling from the last iterations, masks, memory, and
stores built from an example trajectory (its shapes and dtypes, the sizes given by hand giving the same stores)."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from jcomps import envs
from jcomps.training import acting, buffers, ppo
from jcomps.training.acting import Trajectory

T, B, OBS, ACT = 3, 4, 2, 1


def _batch(returns, tag):
    """A batch whose trajectory b has return returns[b] and observations all equal to tag + b."""
    r = np.asarray(returns, np.float32)
    obs = np.broadcast_to((tag + np.arange(len(r), dtype=np.float32))[None, :, None], (T, len(r), OBS))
    ones = np.ones((T, len(r)), np.float32)
    return Trajectory(jnp.asarray(obs), jnp.zeros((T, len(r), ACT)), jnp.asarray(-ones), jnp.asarray(ones * r / T),
                      jnp.zeros((T, len(r))), jnp.asarray(ones), jnp.zeros((T, len(r))),
                      jnp.full((len(r), OBS), tag, jnp.float32))


@settings(max_examples=15)
@given(st.lists(st.lists(st.floats(-100, 100, width=32), min_size=B, max_size=B), min_size=1, max_size=6),
       st.integers(1, 8))
def test_skilled_store_keeps_the_true_top_k(batches, k):
    store = buffers.skilled_init_like(_batch(batches[0], 0.0), k)
    update = jax.jit(buffers.skilled_update)
    everything = []
    for i, rets in enumerate(batches):
        store = update(store, _batch(rets, 100.0 * i))
        everything += [(r, 100.0 * i + b) for b, r in enumerate(rets)]
    expected = sorted((np.float32(np.sum(np.full(T, np.float32(r) / T, np.float32))) for r, _ in everything),
                      reverse=True)[:k]
    kept = np.sort(np.asarray(store.returns)[np.isfinite(store.returns)])[::-1]
    np.testing.assert_allclose(kept, expected, rtol=1e-5, atol=1e-4)
    # Each kept row's data travels with its return: the obs tag identifies the trajectory.
    by_tag = {tag: np.sum(np.full(T, np.float32(r) / T, np.float32)) for r, tag in everything}
    for row in range(min(k, len(everything))):
        tag = float(store.obs[0, row, 0])
        np.testing.assert_allclose(store.returns[row], by_tag[tag], rtol=1e-5, atol=1e-4)


def test_offpolicy_samples_only_the_last_iterations():
    capacity = 3
    ring = buffers.recent_init_like(_batch(np.zeros(B), 0.0), capacity)
    for i in range(5):  # iterations 0..4; the ring keeps 2, 3, 4
        ring = buffers.recent_add(ring, _batch(np.zeros(B), 100.0 * i))
    off = buffers.sample_offpolicy(ring, 12, jax.random.PRNGKey(0))
    chex.assert_shape(off.traj.obs, (T, 12, OBS))
    chex.assert_shape(off.traj.last_obs, (12, OBS))
    tags = np.asarray(off.traj.obs[0, :, 0])
    assert set(np.floor(tags / 100).astype(int)) == {2, 3, 4}
    assert len(set(tags.tolist())) == 12  # without replacement
    np.testing.assert_array_equal(off.mask, np.ones(12))
    np.testing.assert_array_equal(np.floor(tags / 100) * 100, off.traj.last_obs[:, 0])
    np.testing.assert_array_equal(off.traj.log_prob, -np.ones((T, 12)))


def test_offpolicy_masks_rows_it_cannot_fill():
    ring = buffers.recent_add(buffers.recent_init_like(buffers.trajectory_spec(T, B, OBS, ACT), 4),
                              _batch(np.zeros(B), 0.0))  # M = 1
    off = buffers.sample_offpolicy(ring, 6, jax.random.PRNGKey(1))
    np.testing.assert_array_equal(np.sort(np.asarray(off.mask)), [0, 0, 1, 1, 1, 1])
    valid_tags = np.asarray(off.traj.obs[0, :, 0])[np.asarray(off.mask) > 0]
    assert sorted(valid_tags.tolist()) == [0.0, 1.0, 2.0, 3.0]


def test_sequence_write_fills_one_slot_and_marks_it():
    example = buffers.trajectory_spec(T, B, OBS, ACT)
    stores = buffers.sequence_init_like(example, 5, 2, 3)
    skilled = buffers.skilled_update(buffers.skilled_init_like(example, 2), _batch([1.0, 5.0, 3.0, 2.0], 7.0))
    ring = buffers.recent_add(buffers.recent_init_like(example, 1), _batch(np.zeros(B), 9.0))
    off = buffers.sample_offpolicy(ring, 3, jax.random.PRNGKey(0))
    out = jax.jit(buffers.sequence_write)(stores, jnp.int32(2), skilled, off)
    np.testing.assert_array_equal(out.task_valid, [False, False, True, False, False])
    chex.assert_trees_all_equal(jax.tree.map(lambda x: x[2], out.skilled), skilled)
    chex.assert_trees_all_equal(jax.tree.map(lambda x: x[0], out.skilled),
                                jax.tree.map(lambda x: x[0], stores.skilled))


def test_recent_capacity_is_five_percent_of_the_budget_rounded_up():
    assert buffers.recent_capacity(1000) == 50
    assert buffers.recent_capacity(500) == 25
    assert buffers.recent_capacity(300) == 15
    assert buffers.recent_capacity(10) == 1


def test_the_stores_memory_is_what_they_allocate_and_a_40_task_ant_sequence_fits():
    small = buffers.sequence_init(3, 5, 2, 4, 6, 2)
    assert buffers.sequence_bytes(3, 5, 2, 4, 6, 2) == sum(x.nbytes for x in jax.tree.leaves(small))
    # The paper's sizes (40 tasks, T = 200, 20 skilled and 100 off-policy trajectories, Ant obs 27, action 8):
    # about 144 MiB per seed, so 6 seeds of a 40-task Ant study hold their experience in under 1 GiB.
    assert 140 < buffers.sequence_bytes(40, 200, 20, 100, 27, 8) / 2**20 < 150


def test_pick_rows_masks_what_it_cannot_fill():
    idx, ok = buffers.pick_rows(jax.random.PRNGKey(0), jnp.array([True, False, True]), 5)
    chex.assert_shape(idx, (5,))
    np.testing.assert_array_equal(np.sort(np.asarray(idx)[np.asarray(ok) > 0]), [0, 2])
    assert float(ok.sum()) == 2.0


def test_non_finite_trajectories_stay_out_of_both_stores():
    # Trajectory 1 has the highest return but a NaN observation; trajectory 3 an infinite last observation.
    batch = _batch([1.0, 50.0, 2.0, 40.0], 0.0)
    batch = batch._replace(obs=batch.obs.at[1, 1, 0].set(jnp.nan), last_obs=batch.last_obs.at[3, 1].set(jnp.inf))
    np.testing.assert_array_equal(buffers.finite_trajectories(batch), [True, False, True, False])
    skilled = buffers.skilled_update(buffers.skilled_init_like(batch, 3), batch)
    assert sorted(np.asarray(skilled.returns).tolist(), reverse=True)[:2] == [2.0, 1.0]
    assert np.isneginf(np.asarray(skilled.returns)).sum() == 1
    assert all(np.all(np.isfinite(np.asarray(x))) for x in (skilled.obs, skilled.action, skilled.valid))
    recent = buffers.recent_add(buffers.recent_init_like(batch, 2), batch)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(recent.traj))
    for seed in range(5):
        off = buffers.sample_offpolicy(recent, 4, jax.random.PRNGKey(seed))
        # Only the two finite trajectories can be drawn: tags 0 and 2 in the observations.
        assert float(off.mask.sum()) == 2.0
        picked = np.asarray(off.traj.obs[0, :, 0])[np.asarray(off.mask) > 0]
        assert sorted(picked.tolist()) == [0.0, 2.0]
        assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(off.traj))


def _shapes(tree):
    """(shape, dtype) of every leaf of ``tree``, in order, with its structure's text (class names)."""
    return str(jax.tree.structure(tree)), [(x.shape, jnp.dtype(x.dtype)) for x in jax.tree.leaves(tree)]


def test_the_stores_shapes_and_dtypes():
    # The stores are carried in method states and checkpoints: these shapes and dtypes must not change.
    n, K, N, C, f32 = 5, 7, 9, 11, jnp.float32
    step, last = lambda k, *s: [((n, T, k) + s, f32)], lambda k: [((n, k, OBS), f32)]  # noqa: E731
    per_step = lambda k: step(k, OBS) + step(k, ACT) + 5 * step(k) + last(k)  # noqa: E731
    assert _shapes(buffers.sequence_init_like(buffers.trajectory_spec(T, B, OBS, ACT), n, K, N))[1] == (
        step(K, OBS) + step(K, ACT) + step(K) + [((n, K), f32)] + per_step(N) + [((n, N), f32), ((n,), jnp.bool_)])
    assert _shapes(buffers.recent_init_like(buffers.trajectory_spec(T, B, OBS, ACT), C))[1] == (
        [((C, T, B, OBS), f32), ((C, T, B, ACT), f32)] + [((C, T, B), f32)] * 5 + [((C, B, OBS), f32)]
        + [((C, B), jnp.bool_), ((), jnp.int32)])
    assert _shapes(buffers.transitions_init_like(buffers.trajectory_spec(T, B, OBS, ACT), n, C))[1] == (
        [((n, C, OBS), f32), ((n, C, ACT), f32), ((n, C), f32), ((n, C, OBS), f32), ((n, C), f32), ((n, C), f32),
         ((n,), jnp.int32)])


def _round_trip(example, batch):
    """Each store built from ``example``, empty and after ``batch`` is written into it (as the methods write:
    skilled_update, recent_add then sample_offpolicy of every row, sequence_write into slot 1, transitions_add)."""
    S = batch.reward.shape[1]
    empty = dict(skilled=buffers.skilled_init_like(example, S), recent=buffers.recent_init_like(example, 2),
                 seq=buffers.sequence_init_like(example, 3, S, S), trans=buffers.transitions_init_like(example, 2, T * S))
    skilled = buffers.skilled_update(empty["skilled"], batch)
    off = buffers.sample_offpolicy(buffers.recent_add(empty["recent"], batch), S, jax.random.PRNGKey(0))
    full = dict(skilled=skilled, off=off, seq=buffers.sequence_write(empty["seq"], jnp.int32(1), skilled, off),
                trans=buffers.transitions_add(empty["trans"], jnp.int32(0), batch))
    return empty, full


def test_stores_start_empty_and_hold_what_is_written():
    batch = _batch([3.0, 1.0, 2.0, 0.0], 10.0)  # trajectory b has observations 10 + b
    empty, full = _round_trip(batch, batch)
    # Empty: nothing counts as data until it is written.
    assert np.all(np.isneginf(empty["skilled"].returns)) and not np.any(empty["recent"].finite)
    assert int(empty["recent"].iterations) == 0 and not np.any(empty["seq"].task_valid)
    assert not np.any(empty["seq"].offpolicy.mask) and not np.any(empty["trans"].count)
    # The skilled store holds the batch's trajectories by falling return, their data with them.
    np.testing.assert_array_equal(full["skilled"].returns, [3.0, 2.0, 1.0, 0.0])
    np.testing.assert_array_equal(full["skilled"].obs[0, :, 0], [10.0, 12.0, 11.0, 13.0])
    # The off-policy sample of the one iteration held is the batch itself, in some order, every row unmasked.
    order = np.asarray(full["off"].traj.obs[0, :, 0] - 10.0).astype(int)
    assert sorted(order.tolist()) == [0, 1, 2, 3] and np.all(full["off"].mask == 1.0)
    reordered = jax.tree.map(lambda x: jnp.take(x, order, axis=1), batch._replace(last_obs=None))
    chex.assert_trees_all_equal(full["off"].traj, reordered._replace(last_obs=batch.last_obs[order]))
    # The sequence store holds them in slot 1 only, and marks only slot 1.
    np.testing.assert_array_equal(full["seq"].task_valid, [False, True, False])
    chex.assert_trees_all_equal(jax.tree.map(lambda x: x[1], full["seq"].skilled), full["skilled"])
    chex.assert_trees_all_equal(jax.tree.map(lambda x: x[1], full["seq"].offpolicy), full["off"])
    assert np.all(np.isneginf(np.asarray(full["seq"].skilled.returns)[[0, 2]]))
    # The replay slot holds the batch's T·B transitions, time-major (row t·B + b is step t of trajectory b), each
    # step's next observation the following step's, the last one's the observation reached; the other slot is
    # untouched.
    replay = full["trans"]
    for t in range(T):
        for b in range(B):
            row = t * B + b
            np.testing.assert_array_equal(replay.obs[0, row], batch.obs[t, b])
            np.testing.assert_array_equal(replay.reward[0, row], batch.reward[t, b])
            np.testing.assert_array_equal(replay.next_obs[0, row],
                                          batch.obs[t + 1, b] if t + 1 < T else batch.last_obs[b])
    np.testing.assert_array_equal(replay.count, [T * B, 0])


def test_stores_from_an_example_are_those_sized_by_hand():
    example = _batch(np.arange(B), 3.0)  # arrays or their shapes: the same stores
    for spec in (example, jax.eval_shape(lambda: example), buffers.trajectory_spec(T, B, OBS, ACT)):
        chex.assert_trees_all_equal(buffers.skilled_init_like(spec, 6), buffers.skilled_init(T, 6, OBS, ACT))
        chex.assert_trees_all_equal(buffers.recent_init_like(spec, 2), buffers.recent_init(2, T, B, OBS, ACT))
        chex.assert_trees_all_equal(buffers.sequence_init_like(spec, 3, 4, 5),
                                    buffers.sequence_init(3, T, 4, 5, OBS, ACT))
        chex.assert_trees_all_equal(buffers.transitions_init_like(spec, 3, 8),
                                    buffers.transitions_init(3, 8, OBS, ACT))
    assert np.all(np.isneginf(buffers.skilled_init_like(example, 6).returns))


def test_stores_take_the_examples_dtypes_and_keep_them_when_written():
    half = jax.tree.map(lambda x: x.astype(jnp.bfloat16), _batch([1.5, 0.25, 2.0, 0.5], 4.0))
    empty, full = _round_trip(jax.eval_shape(lambda: half), half)
    for name, store in [*empty.items(), *full.items()]:
        leaves = [x for x in jax.tree.leaves(store) if jnp.issubdtype(x.dtype, jnp.floating)]
        dtypes = {x.dtype for x in leaves} - ({jnp.dtype(jnp.float32)} if name in ("off", "seq") else set())
        assert dtypes == {jnp.dtype(jnp.bfloat16)}, f"{name}: {dtypes}"  # the off-policy mask is float32 by design
    # A write neither promotes a dtype (a checkpoint's store would change type) nor rounds a value it stores.
    for name in ("skilled", "seq", "trans"):
        chex.assert_trees_all_equal_dtypes(empty[name], full[name])
    np.testing.assert_array_equal(np.asarray(full["skilled"].returns, np.float32), [2.0, 1.5, 0.5, 0.25])
    np.testing.assert_array_equal(np.asarray(full["trans"].obs[0]), np.asarray(half.obs.reshape(-1, OBS)))


def test_rollout_example_has_a_rollouts_shapes():
    family = envs.make("point_goal")
    policy = jax.jit(ppo.init_params, static_argnums=(0, 1))(ppo.PPOConfig(), family, jax.random.PRNGKey(0)).policy
    example = buffers.rollout_example(family, 3)
    assert all(isinstance(x, jax.ShapeDtypeStruct) for x in jax.tree.leaves(example))
    task = family.make_task(jnp.float32(family.task_values[-1]))
    ran = jax.jit(acting.rollout, static_argnums=(0, 4))(family, policy, task, jax.random.PRNGKey(1), 3)
    assert _shapes(example) == _shapes(ran)
    traced = jax.jit(lambda p: jnp.zeros(buffers.rollout_example(family, 3).obs.shape))(policy)  # a traced policy
    chex.assert_shape(traced, (family.max_steps, 3, family.obs_size))
    # The stores a method builds from it are those of the family's sizes given by hand.
    T_max, O, A = family.max_steps, family.obs_size, family.action_size
    chex.assert_trees_all_equal(buffers.sequence_init_like(example, 2, 4, 5),
                                buffers.sequence_init(2, T_max, 4, 5, O, A))
    chex.assert_trees_all_equal(buffers.recent_init_like(example, 2), buffers.recent_init(2, T_max, 3, O, A))
