"""The persistent compile cache (``jcomps.runner.compile_cache``): a program with host callbacks (our progress hooks)
compiled in one process is loaded from the cache by the next, and its callbacks still reach the host; ``none``
turns the cache off; the directory follows ``XDG_CACHE_HOME``. Config values that are not finite are refused."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import pytest

from jcomps import continual
from jcomps.methods import comps
from jcomps.runner import compile_cache
from jcomps.training import meta, ppo

CHILD = r"""
import json, sys
from jcomps.runner import compile_cache
directory = compile_cache.configure(sys.argv[1])
import jax, jax.numpy as jnp
from jax._src import monitoring
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
events = []
monitoring.register_event_listener(lambda name, **kw: events.append(name))
seen = []

def f(x):
    def body(c, i):
        c = jnp.tanh(c @ c) + i
        jax.debug.callback(lambda v: seen.append(float(v)), c[0, 0])
        return c, c.sum()
    return jax.lax.scan(body, x, jnp.arange(7.0))

out = jax.block_until_ready(jax.jit(f)(jnp.eye(8) * 0.1))
print(json.dumps({"directory": directory, "callbacks": len(seen), "total": float(out[1].sum()),
                  "hits": events.count("/jax/compilation_cache/cache_hits"),
                  "patched": compile_cache.callbacks_cached()}))
"""


def _child(directory):
    proc = subprocess.run([sys.executable, "-c", CHILD, directory], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_a_program_with_callbacks_is_loaded_from_the_cache_with_its_callbacks(tmp_path):
    first = _child(str(tmp_path / "cache"))
    second = _child(str(tmp_path / "cache"))
    assert first["patched"] and first["directory"] == str(tmp_path / "cache")
    assert first["hits"] == 0 and second["hits"] >= 1  # the second process compiled nothing it had stored
    assert first["callbacks"] == second["callbacks"] == 7  # the loaded program still reports to the host
    assert first["total"] == second["total"]
    assert any(name.startswith("jit_f-") for name in os.listdir(tmp_path / "cache"))


def test_none_turns_it_off(tmp_path):
    off = _child("none")
    assert off["directory"] is None and off["hits"] == 0


def test_default_directory_follows_xdg(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert compile_cache.default_directory() == os.path.join(str(tmp_path), "jcomps", "xla")
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert compile_cache.default_directory() == os.path.join(os.path.expanduser("~"), ".cache", "jcomps", "xla")


def test_an_unwritable_directory_is_refused():
    with pytest.raises(ValueError, match="compile_cache"):
        compile_cache.configure("/proc/jcomps-cache")


@pytest.mark.parametrize("make, field", [
    (lambda: ppo.PPOConfig(learning_rate=math.inf), "learning_rate"),
    (lambda: ppo.PPOConfig(clip_epsilon=math.nan), "clip_epsilon"),
    (lambda: meta.MetaConfig(outer_learning_rate=-math.inf), "outer_learning_rate"),
    (lambda: comps.CoMPSConfig(ppo=ppo.PPOConfig(hidden_sizes=(64,)), max_tasks=2), None),
])
def test_non_finite_config_values_are_refused(make, field):
    if field is None:  # finite values pass
        make()
        return
    with pytest.raises(ValueError, match=f"invalid config value {field}=.*allowed: a finite number"):
        make()


def test_heldout_budget_by_family():
    # Off by default (the zero-shot return only); the curve asked for brings the family's budget with it.
    off = continual.EvalConfig()
    assert off.heldout_budget is None and off.heldout_iterations == 0
    assert off.resolve("point_goal").heldout_budget == 0 and not off.resolve("point_goal").heldout_measured
    assert off.resolve("point_goal").heldout_run == 1
    config = continual.EvalConfig(heldout_iterations=5)
    assert config.resolve("point_goal").heldout_budget == 50 and config.resolve("point_goal").heldout_measured
    assert config.resolve("cheetah_vel").heldout_budget == 0 and config.resolve("metaworld").heldout_budget == 0
    assert config.resolve("cheetah_vel").heldout_measured
    assert continual.EvalConfig(heldout_budget=7).resolve("cheetah_vel").heldout_budget == 7
    assert continual.EvalConfig(heldout_budget=7).resolve("cheetah_vel").heldout_measured
    with pytest.raises(ValueError, match="resolve"):
        config.heldout_run
