"""Tests of a program's members (``jcomps.runner.members``): how seeds and grid points fill the devices, and their
random streams."""

import jax
import numpy as np

from jcomps import continual, methods
from jcomps.runner import grid, members


def test_seeds_fill_the_devices():
    assert members.num_devices(4, 2) == 2 and members.num_devices(3, 2) == 2 and members.num_devices(1, 8) == 1
    assert members.padded_seeds(3, 2) == 4 and members.padded_seeds(4, 2) == 4
    assert members.padded_seeds(5, 1) == 5
    assert members.padded_seeds(6, 4) == 8


def test_members_are_point_major_and_padding_repeats_point_0_with_the_next_seeds():
    cls = methods.config_class("ppo_tl")
    axes = grid.parse(["learning_rate=0.01,0.001,0.0001"], {"ppo_tl": cls})
    spec = grid.programs("ppo_tl", cls(), axes)[0]
    point, seed, hparams = members.layout(spec, 3, 5, 4)  # 9 members on 4 devices: 3 padding members
    assert point == [0, 0, 0, 1, 1, 1, 2, 2, 2, 0, 0, 0]
    assert seed == [5, 6, 7] * 3 + [8, 9, 10]
    np.testing.assert_array_equal(hparams["learning_rate"], np.float32([0.01, 0.001, 0.0001, 0.01]).repeat(3))
    # Without a grid the members are the seeds, as before grids existed.
    plain, = grid.programs("ppo_tl", cls(), ())
    assert members.layout(plain, 3, 0, 2) == ([0, 0, 0, 0], [0, 1, 2, 3], {})


def _keys_drawn_from(key) -> set:
    """Keys a method can draw from its root ``key`` in the first two generations of split/fold_in."""
    out = set()
    for k in [key]:
        for n in range(1, 6):
            for child in jax.random.split(k, n):
                out.add(tuple(np.asarray(child).tolist()))
                out.update(tuple(np.asarray(g).tolist()) for g in jax.random.split(child, 4))
        out.update(tuple(np.asarray(jax.random.fold_in(k, i)).tolist()) for i in range(16))
    return out | {tuple(np.asarray(key).tolist())}


def test_evaluation_keys_never_equal_a_key_the_method_draws():
    seeds = [0, 1, 2]
    eval_keys = [members.task_eval_keys(seeds)] + [members.heldout_keys(seeds, m) for m in range(4)]
    for s, method_key in enumerate(members.method_keys(seeds)):
        drawn = _keys_drawn_from(method_key)
        evaluations = {tuple(np.asarray(k[s]).tolist()) for k in eval_keys}
        # The backward-transfer keys are folded further per task and per previous task (continual.evaluate_task).
        evaluations |= {tuple(np.asarray(jax.random.fold_in(jax.random.fold_in(eval_keys[0][s], i), d)).tolist())
                        for i in range(4) for d in range(3)}
        # So are the learnt tasks' evaluation keys, apart from them (continual.learnt_key).
        learnt = {tuple(np.asarray(continual.learnt_key(eval_keys[0][s], j)).tolist()) for j in range(4)}
        assert len(learnt) == 4 and not learnt & evaluations
        evaluations |= learnt
        assert not drawn & evaluations
    # The derivation this replaces (evaluation keys folded from the method's own root) collides: the check bites.
    root = jax.random.PRNGKey(0)
    assert tuple(np.asarray(jax.random.fold_in(root, 1)).tolist()) in _keys_drawn_from(root)
