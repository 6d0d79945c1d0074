"""The exploration std's three modes (``PPOConfig.std_mode``) for every method that carries a Gaussian policy from
task to task, and the plasticity measures each task reports (``jcomps.training.plasticity``)."""

import dataclasses
import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jcomps import envs, methods
from jcomps.training import networks, plasticity, ppo

FAMILY = envs.make("point_goal")
INIT_STD = 0.3
TINY_PPO = ppo.PPOConfig(num_trajectories=2, num_updates=2, minibatch_size=16, hidden_sizes=(8, 8), budget=3,
                         init_std=INIT_STD)
TINY_META = dict(num_meta_steps=1, num_outer_steps=2, inner_trajectories=2, skilled_trajectories=2)
# One of each kind of learner: PPO alone, PPO and the meta step, MAML's inner and outer steps, PNC's active column
# and distillation (with its active column carried over, so that the reset is what restores its std).
METHODS = ("ppo_tl", "comps", "maml_tl", "pnc")


def _config(name: str, std_mode: str):
    base = methods.default_config(name, FAMILY)
    changes = {"ppo": dataclasses.replace(TINY_PPO, std_mode=std_mode)}
    if hasattr(base, "meta"):
        changes.update(meta=dataclasses.replace(base.meta, **TINY_META), max_tasks=2, num_skilled=2, num_offpolicy=4)
    if name == "pnc":
        changes["reset_active"] = False
    return dataclasses.replace(base, **changes)


def _log_stds(state) -> dict:
    """Every exploration log-std a method's state holds, by where it is."""
    out = {"params": state.params.policy["log_std"]}
    if hasattr(state, "meta"):
        out["meta"] = state.meta.policy["log_std"]
    if hasattr(state, "active"):
        out["active"] = state.active["log_std"]
    return out


def _with_log_std(state, log_std):
    """``state`` with every policy's log-std set to ``log_std`` (as a learnt std would have left it)."""
    def set_std(policy):
        return {**policy, "log_std": jnp.full_like(policy["log_std"], log_std)}

    state = state._replace(params=state.params._replace(policy=set_std(state.params.policy)))
    if hasattr(state, "meta"):
        state = state._replace(meta=state.meta._replace(policy=set_std(state.meta.policy)))
    if hasattr(state, "active"):
        state = state._replace(active=set_std(state.active))
    return state


@functools.lru_cache(maxsize=None)
def _learn_one(name: str, std_mode: str, log_std=None):
    """(state before, state after, TaskMetrics) of one task of ``name`` in ``std_mode`` from its initial state (with
    every log-std set to ``log_std`` if given); each compiled once for the module."""
    method = methods.make(name, FAMILY, _config(name, std_mode))
    state = method.init(jax.random.PRNGKey(0))
    if log_std is not None:
        state = _with_log_std(state, log_std)
    after, metrics = jax.jit(method.learn_task)(state, envs.task_at(FAMILY, 0))
    return state, after, metrics


@pytest.mark.parametrize("name", METHODS)
def test_a_fixed_std_is_bit_for_bit_unchanged_after_a_task(name):
    before, after, metrics = _learn_one(name, "fixed")
    for where, log_std in _log_stds(after).items():
        np.testing.assert_array_equal(np.asarray(log_std), np.asarray(_log_stds(before)[where]), err_msg=where)
        np.testing.assert_array_equal(np.asarray(log_std), np.float32(np.log(np.float32(INIT_STD))), err_msg=where)
    # The mean did learn: the std alone was held.
    moved = jax.tree.map(lambda a, b: bool(jnp.any(a != b)), before.params.policy["mean"], after.params.policy["mean"])
    assert any(jax.tree.leaves(moved))
    health = metrics.policy_health
    np.testing.assert_allclose([float(health.std_start), float(health.std_end)], INIT_STD, rtol=1e-6)


@pytest.mark.parametrize("name", ["ppo_tl", "comps"])  # maml_tl and pnc: tests/test_baselines.py
def test_a_reset_std_starts_each_task_at_init_std_and_is_learnt_within_it(name):
    narrowed = np.log(0.05)  # what a learnt std carried from an earlier task might be
    _, _, metrics = _learn_one(name, "reset", narrowed)
    health = metrics.policy_health
    np.testing.assert_allclose(float(health.std_start), INIT_STD, rtol=1e-6)
    assert float(health.std_end) != pytest.approx(INIT_STD, rel=1e-7)  # learnt within the task


def test_a_learnt_std_is_carried_into_the_next_task():
    _, _, metrics = _learn_one("ppo_tl", "learnt", np.log(0.05))
    np.testing.assert_allclose(float(metrics.policy_health.std_start), 0.05, rtol=1e-6)


def test_comps_holds_the_meta_steps_std_exactly_when_the_rl_steps_is_fixed():
    # (That a held std stays bit for bit through the meta step: test_a_fixed_std_is_bit_for_bit_unchanged_after_a_task.)
    from jcomps.methods import comps

    assert comps.meta_config(_config("comps", "fixed")).hold_std is True
    assert comps.meta_config(_config("comps", "reset")).hold_std is False
    held = dataclasses.replace(_config("comps", "learnt"), meta=dataclasses.replace(_config("comps", "learnt").meta,
                                                                                    hold_std=True))
    assert comps.meta_config(held).hold_std is True  # given, not followed


def test_bad_std_mode_names_the_field():
    with pytest.raises(ValueError, match="std_mode"):
        ppo.PPOConfig(std_mode="frozen")


def test_saturated_fraction_counts_units_saturated_on_nearly_every_valid_state():
    n = 200
    always = jnp.full((n,), 0.995)  # saturated everywhere
    mostly = jnp.where(jnp.arange(n) < 196, -0.999, 0.0)  # on 98% of the states: not saturated
    never = jnp.zeros((n,))
    hidden = [jnp.stack([always, mostly, never, always], axis=-1), jnp.stack([never, never], axis=-1)]
    valid = jnp.ones((n,))
    np.testing.assert_allclose(np.asarray(plasticity.saturated_fraction(hidden, valid)), [0.5, 0.0])
    # Invalid states do not count: unsaturated only where invalid, the unit is saturated.
    valid = jnp.where(jnp.arange(n) < 196, 1.0, 0.0)
    np.testing.assert_allclose(np.asarray(plasticity.saturated_fraction(hidden, valid)), [0.75, 0.0])
    # No valid state: nothing is saturated.
    np.testing.assert_allclose(np.asarray(plasticity.saturated_fraction(hidden, jnp.zeros((n,)))), [0.0, 0.0])


def test_policy_health_reads_std_entropy_and_each_layers_saturation():
    params = networks.init_actor_critic(jax.random.PRNGKey(0), 3, 2, (4, 5), 0.2)
    big = {**params.policy, "mean": [{**params.policy["mean"][0], "w": params.policy["mean"][0]["w"] * 1e4},
                                     *params.policy["mean"][1:]], "log_std": jnp.log(jnp.array([0.1, 0.4]))}
    obs = jax.random.normal(jax.random.PRNGKey(1), (6, 4, 3))
    states = plasticity.States(obs, jnp.ones((6, 4)))
    health = plasticity.policy_health(networks.GAUSSIAN, params.policy, big, states, states)
    chex.assert_shape(health.saturated_start, (2,))
    np.testing.assert_allclose(float(health.std_start), 0.2, rtol=1e-6)
    np.testing.assert_allclose(float(health.std_end), 0.25, rtol=1e-6)
    np.testing.assert_allclose(float(health.entropy_end), float(networks.gaussian_entropy(big["log_std"])), rtol=1e-6)
    assert float(health.saturated_start[0]) == 0.0  # a fresh orthogonal layer on unit-scale inputs
    assert float(health.saturated_end[0]) > 0.5  # first-layer weights × 10⁴: most units pinned at ±1


def test_the_calibrated_families_fix_the_std_and_earlier_runs_read_as_learnt():
    """The families with a calibrated fixed std default to it for every PPO-based method (the same RL-step setting
    for every rung and baseline); MetaWorld, not calibrated, learns it; a run.json made before the modes existed
    lacks ``std_mode`` and is read as the learnt std it ran with."""
    from jcomps import configs

    for family, std in (("point_goal", 0.5), ("cheetah_vel", 0.15), ("ant_dir", 0.15), ("ant_goal", 0.1)):
        for name in (m for m in methods.METHODS if m != "pearl"):
            config = methods.default_config(name, family).ppo
            assert (config.std_mode, config.init_std) == ("fixed", std), (name, family)
    assert methods.default_config("comps", "metaworld").ppo.std_mode == "learnt"
    stored = configs.to_json(methods.default_config("comps", "ant_dir"))
    assert methods.resolve_config("comps", "ant_dir", stored=stored).ppo.std_mode == "fixed"
    del stored["ppo"]["std_mode"]
    assert methods.resolve_config("comps", "ant_dir", stored=stored).ppo.std_mode == "learnt"
