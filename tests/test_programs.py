"""Tests of the compiled programs' machinery (``jcomps.runner.programs``)."""

import time

import jax
import numpy as np

from jcomps import continual, methods
from jcomps.runner import members, programs


def test_a_long_compile_keeps_saying_so():
    beats = []
    with programs._heartbeat(lambda: beats.append(1), interval=0.05):
        time.sleep(0.3)
    count = len(beats)
    time.sleep(0.15)
    assert count >= 2 and len(beats) == count  # beats while the block runs, none after


def test_a_program_compiles_once_ahead_of_time_and_says_how_long_it_took():
    program = programs.Programs().get("ppo_tl", "point_goal", methods.default_config("ppo_tl", "point_goal"),
                                      continual.EvalConfig(), 1, 1)
    keys = members.method_keys([0, 1])
    times = program.compile("init", keys, {})
    assert 0 <= times.trace_seconds <= times.seconds and not times.cached  # the compile cache is off in tests
    assert program.compile("init", keys, {}) is None and program.traces["init"] == 1
    # The ahead-of-time program computes what ``init`` gives.
    for a, b in zip(jax.tree.leaves(program.compiled["init"](keys, {})), jax.tree.leaves(program.init(keys))):
        np.testing.assert_array_equal(a, b)


def test_a_part_called_without_compile_counts_each_signature_it_is_traced_for():
    program = programs.Programs().get("ppo_tl", "point_goal", methods.default_config("ppo_tl", "point_goal"),
                                      continual.EvalConfig(), 1, 1)
    assert program.traces == dict.fromkeys(programs.PARTS, 0)
    program.init(members.method_keys([0, 1]))
    program.init(members.method_keys([2, 3]))  # same shapes: the jitted program is reused
    assert program.traces["init"] == 1
    program.init(members.method_keys([0, 1, 2]))  # three members: traced again
    assert program.traces == {"init": 2, "learn": 0, "evaluate_task": 0, "measure": 0}
