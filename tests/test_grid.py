"""Tests of hyperparameter grids (``--grid``): parsing and validation, the compiled grid program against separate
runs, resume, results entries and the report's grid table."""

import json
import os
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jcomps import continual, envs, methods
from jcomps.methods import comps, ppo_tl
from jcomps.runner import experiment, grid, programs, rundir

TINY = ["--budget", "3", "--num-trajectories", "2", "--num-updates", "1", "--minibatch-size", "16",
        "--heldout-iterations", "1", "--heldout-budget", "3", "--backward-tasks", "2"]
RUN = ["--methods", "ppo_tl", "--num-tasks", "3", "--seeds", "2", "--chunk-tasks", "1"]
# A traced axis (learning_rate: one program) and a shape-changing one (hidden_sizes: one program per value).
GRID = ["--grid", "learning_rate=0.01,0.001", "--grid", "hidden_sizes=8,4"]
# Entries in product order (--grid order); the programs group them by hidden sizes.
KEYS = ["ppo_tl[learning_rate=0.01,hidden_sizes=8]", "ppo_tl[learning_rate=0.01,hidden_sizes=4]",
        "ppo_tl[learning_rate=0.001,hidden_sizes=8]", "ppo_tl[learning_rate=0.001,hidden_sizes=4]"]


def _raw(out, name):
    with np.load(out / "raw" / f"{name}.npz") as f:
        return {k: f[k] for k in f.files if k != "seconds"}


@pytest.fixture(scope="module")
def grid_run(tiny_run):
    """An uninterrupted grid run: 2 programs (hidden sizes) of 2 traced learning rates × 2 seeds each."""
    return tiny_run(TINY + RUN + GRID, "grid")


@pytest.fixture(scope="module")
def plain_run(tiny_run):
    """The same run without a grid, at one of its points (learning rate 0.001, hidden sizes 8). Its ppo_tl
    program is tests/test_experiment.py's, compiled once when both files run in one session."""
    return tiny_run(TINY + RUN + ["--learning-rate", "0.001", "--hidden-sizes", "8"], "plain")


# --- parsing and validation -------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv,message", [
    (["--grid", "nope=1,2"], "--grid nope: unknown field"),
    (["--methods", "ppo_tl", "--grid", "max_tasks=5,6"],
     "--grid max_tasks: unknown field; no method in --methods \\(ppo_tl\\)"),
    (["--grid", "learning_rate=-1,0.01"], "--grid learning_rate=-1.0: invalid config value learning_rate"),
    (["--grid", "init_std=0"], "--grid init_std=0.0: invalid"),
    (["--grid", "learning_rate="], "--grid learning_rate: empty list of values"),
    (["--grid", "learning_rate=0.1,,0.2"], "--grid learning_rate: an empty value"),
    (["--grid", "learning_rate=fast"], "--grid learning_rate: cannot parse 'fast'"),
    (["--grid", "hidden_sizes=8,4y4"], "--grid hidden_sizes: cannot parse '4y4'"),
    (["--grid", "budget=2.5"], "--grid budget: cannot parse '2.5'"),
    (["--grid", "learning_rate=0.1,0.1"], "--grid learning_rate: value 0.1 given twice"),
    (["--grid", "learning_rate=0.1", "--grid", "learning_rate=0.2"], "--grid learning_rate: given twice"),
    (["--grid", "learning_rate=0.1,0.2", "--learning-rate", "0.3"], "--grid learning_rate: also given as "
                                                                    "--learning-rate"),
    (["--grid", "learning_rate"], "expected FIELD=VALUE"),
    (["--methods", "comps", "--num-tasks", "4", "--grid", "max_tasks=2,8"], "--grid max_tasks=2 is smaller than "
                                                                            "--num-tasks 4"),
])
def test_bad_grids_exit_2_naming_the_field(runner, argv, message, capsys):
    with pytest.raises(SystemExit) as info:
        runner.description_of(argv + ["--out", "/nonexistent/x"])
    assert info.value.code == 2
    assert re.search(message, capsys.readouterr().err)


def test_grid_points_keys_and_programs(runner):
    described = runner.description_of(["--methods", "comps", "ppo_tl", "--num-tasks", "3", "--grid",
                                       "learning_rate=0.01,0.001", "--grid", "max_tasks=3,4", "--grid", "discount=0.9",
                                       "--out", "/nonexistent/x"])
    points = {m: grid.points(m, described.methods[m], described.grid) for m in described.run.methods}
    assert [p.key for p in points["ppo_tl"]] == ["ppo_tl[learning_rate=0.01,discount=0.9]",
                                                 "ppo_tl[learning_rate=0.001,discount=0.9]"]
    assert points["comps"][1].key == "comps[learning_rate=0.01,max_tasks=4,discount=0.9]"
    config = points["comps"][1].config  # a shared name sets every nested config that has it
    assert (config.ppo.learning_rate, config.max_tasks) == (0.01, 4)
    assert config.ppo.discount == config.meta.discount == 0.9
    specs = grid.programs("comps", described.methods["comps"], described.grid)
    # learning_rate (2 values) is traced; max_tasks changes shapes: one program per value; discount has one value.
    assert [(s.label, s.traced, len(s.points)) for s in specs] == [
        ("comps[max_tasks=3]", ("learning_rate",), 2), ("comps[max_tasks=4]", ("learning_rate",), 2)]
    assert grid.traced_fields(comps.CoMPSConfig) >= {"learning_rate", "discount", "outer_learning_rate"}
    assert "hidden_sizes" not in grid.traced_fields(ppo_tl.PPOTLConfig)


def test_with_traced_builds_a_config_without_touching_the_original():
    """A member's traced values, the arguments of its program, become its config's fields (every nested occurrence);
    the configs holding them skip their checks, which concrete values still pass through."""
    base, seen = comps.CoMPSConfig(), {}

    def member(discount, learning_rate):
        seen["config"] = grid.with_traced(base, {"discount": discount, "learning_rate": learning_rate,
                                                 "max_tasks": 7})
        return seen["config"].ppo.learning_rate

    jax.make_jaxpr(member)(0.9, 0.01)
    config = seen["config"]
    assert all(isinstance(x, jax.core.Tracer) for x in (config.ppo.discount, config.meta.discount,
                                                        config.ppo.learning_rate))
    assert config.max_tasks == 40  # not a traced field: left as it is
    assert base == comps.CoMPSConfig() and isinstance(config, comps.CoMPSConfig)
    assert grid.with_traced(base, {"learning_rate": 0.5}).ppo.learning_rate == 0.5
    with pytest.raises(ValueError, match="learning_rate"):
        grid.with_traced(base, {"learning_rate": -1.0})


def test_best_is_the_lowest_iterations_then_the_higher_return():
    entries = [("m", "a", {}), ("m", "b", {}), ("m", "c", {}), ("n", "d", {}), ("n", "e", {})]
    its = {"a": 5.0, "b": 3.0, "c": 3.0, "d": float("nan"), "e": 9.0}
    returns = {"a": 0.0, "b": -2.0, "c": -1.0, "d": 0.0, "e": -5.0}
    assert grid.best(entries, its, returns) == {"m": "c", "n": "e"}


def test_progress_line_names_the_member_behind(console):
    lines = []
    progress = console.Progress("ppo_tl, 2 grid points", 2, 3, 0, lines.append, interval=0.0,
                                   members=["ppo_tl[learning_rate=0.01] seed 0", "ppo_tl[learning_rate=0.001] seed 0"])
    progress.record_iteration(0, 1, 2, 0.5)
    progress.record_iteration(1, 0, 3, 0.1)
    assert lines[-1].startswith("[ppo_tl, 2 grid points] task 1-2/3 iteration 3")
    assert "behind: ppo_tl[learning_rate=0.001] seed 0 (task 1)" in lines[-1]


def test_progress_behind_is_the_member_still_iterating(console):
    """A member that solved its task keeps reporting the iteration it stopped at; the one still running is named."""
    lines = []
    progress = console.Progress("ppo, 2 grid points", 2, 3, 0, lines.append, interval=0.0,
                                   members=["ppo[learning_rate=0.0003] seed 0", "ppo[learning_rate=0.0001] seed 0"])
    for it in range(1, 41):
        progress.record_iteration(0, 0, min(it, 5), 0.3)  # solved at iteration 5, frozen there
        progress.record_iteration(1, 0, it, 0.1)
    assert "iteration 40" in lines[-1]
    assert "behind: ppo[learning_rate=0.0001] seed 0 (task 1)" in lines[-1]


@pytest.mark.parametrize("name", ["ppo_tl", "comps", "maml_tl", "pnc", "pearl"])
def test_every_traced_field_traces(name):
    """Every field a config declares TRACED can be a traced grid axis of the chunk and held-out programs (traced
    only, not compiled)."""
    config = methods.config_class(name)(**({"max_tasks": 2} if name in ("comps", "pearl") else {}))
    traced = tuple(sorted(grid.traced_fields(type(config))))
    program = programs.Programs().get(name, "point_goal", config, continual.EvalConfig(heldout_iterations=2), 1, 1,
                                  traced)
    abstract = lambda tree: jax.tree.map(  # noqa: E731
        lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=program.sharding), tree)
    values = {f: jnp.full((1,), 0.5, jnp.float32) for f in traced}
    states = abstract(jax.eval_shape(program._init, jax.random.PRNGKey(0)[None], values))
    hparams = abstract(values)
    family = envs.make("point_goal")
    seq = abstract(jax.tree.map(lambda x: x[None], envs.sequence(family, num_tasks=2)))
    keys = abstract(jax.random.PRNGKey(0)[None])
    index = abstract(jnp.zeros(1, jnp.int32))
    heldout = envs.held_out(family)

    def bound(seq, keys, index, hparams):  # the run's inputs as a run binds them (here abstract)
        return programs.BoundProgram(program, programs.ProgramInput(seq, index, keys, hparams, heldout))

    metrics = jax.eval_shape(lambda s, q, k, i, h: bound(q, k, i, h).learn_chunk(s, 0, 1), states, seq, keys, index,
                             hparams)[1]
    assert metrics.task.iterations.shape == (1, 1)
    measured = jax.eval_shape(lambda s, q, k, i, h: bound(q, k, i, h).measure(s, k, 1), states, seq, keys, index,
                              hparams)
    assert measured.heldout.iterations.shape[0] == 1 and jax.tree.leaves(measured.learnt)[0].shape[:2] == (1, 2)
    # The runner sizes its host copies from continual's shapes without tracing these programs: they must agree.
    eval_config = continual.EvalConfig(heldout_iterations=2).resolve("point_goal")
    member = lambda tree: jax.tree.map(lambda x: (1,) + x.shape + (x.dtype,), tree)  # noqa: E731
    expected = continual.heldout_shapes(eval_config, len(family.held_out_values), 2)
    assert member(expected) == jax.tree.map(lambda x: x.shape + (x.dtype,), measured)
    evaluation = jax.eval_shape(lambda s, q, k, i, h: bound(q, k, i, h).evaluate_task(s, 0), states, seq, keys, index,
                                hparams)
    assert member(continual.task_evaluation_shapes(eval_config)) == jax.tree.map(lambda x: x.shape + (x.dtype,),
                                                                                  evaluation)


# --- the compiled grid program ----------------------------------------------------------------------------------

def test_results_entries_and_best(grid_run):
    results = json.loads((grid_run / "results.json").read_text())
    assert list(results["methods"]) == KEYS
    assert results["description"]["grid"] == [["learning_rate", [0.01, 0.001]], ["hidden_sizes", [[8], [4]]]]
    for key, entry in results["methods"].items():
        assert entry["method"] == "ppo_tl" and key == grid.key("ppo_tl", [(k, tuple(v) if isinstance(v, list) else v)
                                                                        for k, v in entry["grid"].items()])
        assert np.asarray(entry["iterations_to_success"]).shape == (2, 3)
        assert set(entry["overall"]) == {"iterations_to_success_mean", "iterations_to_success_se", "mean_return"}
    rank = {k: (m["overall"]["iterations_to_success_mean"], -m["overall"]["mean_return"])
            for k, m in results["methods"].items()}
    assert results["best"] == {"ppo_tl": min(rank, key=rank.get)}
    # One checkpoint directory per shape; one raw file per grid point.
    assert sorted(os.listdir(grid_run / "checkpoints")) == ["ppo_tl@hidden_sizes=4", "ppo_tl@hidden_sizes=8"]
    assert sorted(os.listdir(grid_run / "raw")) == sorted(f"{k}.npz" for k in KEYS)


def test_report_table_of_every_grid_point(grid_run):
    text = (grid_run / "significance.md").read_text()
    results = json.loads((grid_run / "results.json").read_text())
    table = text[text.index("## Grid"):]
    rows = [line for line in table.splitlines() if line.startswith("| ppo_tl |")]
    assert len(rows) == 4 and sum("**best**" in r for r in rows) == 1
    best = results["methods"][results["best"]["ppo_tl"]]
    o = best["overall"]
    best_row = next(r for r in rows if "**best**" in r)
    assert f"{o['iterations_to_success_mean']:.2f} ± {o['iterations_to_success_se']:.2f}" in best_row
    assert f"{o['mean_return']:.2f}" in best_row
    assert "| 0.01 | 8 |" in rows[0] and "| 0.001 | 4 |" in rows[3]


def test_traced_values_differ_in_one_program_and_match_separate_runs(grid_run, plain_run):
    """Members of one program with different learning rates learn differently; the members at (0.001, [8]) equal
    the run without a grid at that config to float tolerance, not bit for bit (the learning rate is a runtime
    value in the grid program and a compile-time constant without it, and a device runs 2 members instead of 1
    seed, so XLA rounds some sums and products differently). Integer results (iterations, solved, validity) are
    equal."""
    a, b = _raw(grid_run, KEYS[0]), _raw(grid_run, KEYS[2])
    assert not np.allclose(a["task.per_iteration.value_loss"], b["task.per_iteration.value_loss"])
    plain, member = _raw(plain_run, "ppo_tl"), _raw(grid_run, KEYS[2])
    assert plain.keys() == member.keys()
    for key in plain:
        if plain[key].dtype.kind in "biu":
            np.testing.assert_array_equal(plain[key], member[key], err_msg=key)
        else:
            np.testing.assert_allclose(plain[key], member[key], rtol=1e-4, atol=1e-4, err_msg=key)


def test_one_point_grid_equals_the_run_without_a_grid(runner, plain_run, tmp_path):
    out = tmp_path / "one"
    runner.main(TINY + RUN + ["--grid", "learning_rate=0.001", "--grid", "hidden_sizes=8", "--out", str(out)])
    key = "ppo_tl[learning_rate=0.001,hidden_sizes=8]"
    results = json.loads((out / "results.json").read_text())
    assert list(results["methods"]) == [key] and results["best"] == {"ppo_tl": key}
    a, b = _raw(plain_run, "ppo_tl"), _raw(out, key)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_grid_program_traced_once(runner, grid_run):
    """Each program of the grid run (3 chunks) traced each of its functions once."""
    programs = [p for k, p in runner.PROGRAMS.items() if k[0] == "ppo_tl" and k[3] == ("learning_rate",)]
    assert len(programs) == 2
    for p in programs:
        assert p.traces == {"init": 1, "learn": 1, "evaluate_task": 1, "measure": 1}


def test_killed_and_resumed_grid_run_equals_the_uninterrupted_one(runner, grid_run, tmp_path):
    out = tmp_path / "killed"
    described = runner.description_of(TINY + RUN + GRID + ["--out", str(out)])
    rundir.open_run_dir(str(out), described, resume=False)
    first = grid.programs("ppo_tl", described.methods["ppo_tl"], described.grid)[0]
    assert experiment.run_program(str(out), first, described, resume=False, programs=runner.PROGRAMS,
                                  stop_after_chunks=1) is None
    assert sorted(os.listdir(out / "checkpoints" / "ppo_tl@hidden_sizes=8")) == ["1"]
    runner.main(["--out", str(out), "--resume"])
    for key in KEYS:
        a, b = _raw(grid_run, key), _raw(out, key)
        assert a.keys() == b.keys()
        for k in a:
            np.testing.assert_array_equal(a[k], b[k], err_msg=f"{key} {k}")


def test_resume_refuses_another_grid(runner, grid_run, capsys):
    with pytest.raises(SystemExit) as info:
        runner.main(["--out", str(grid_run), "--resume", "--grid", "learning_rate=0.01,0.002", "--grid",
                     "hidden_sizes=8,4"])
    assert info.value.code == 2 and "grid: run has" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:  # the same axes in another order: another member layout
        runner.main(["--out", str(grid_run), "--resume", "--grid", "hidden_sizes=8,4", "--grid",
                     "learning_rate=0.01,0.001"])
    assert info.value.code == 2 and "grid: run has" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        runner.main(["--out", str(grid_run), "--resume", "--learning-rate", "0.01"])
    assert info.value.code == 2 and "--grid learning_rate: also given as --learning-rate" in capsys.readouterr().err
    runner.main(["--out", str(grid_run), "--resume"])  # the stored grid: everything already finished
    assert capsys.readouterr().out.count("already finished") == 2
