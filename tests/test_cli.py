"""Tests of the config-derived command line and the runner's entry point."""

import dataclasses
import json
import pathlib
import re

import numpy as np
import pytest

from jcomps import configs, envs, methods
from jcomps.methods import ppo_tl
from jcomps.runner import rundir
from jcomps.training import ppo

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_every_config_field_is_an_option(runner):
    args = runner.parse_args(["--out", "/nonexistent/x"])
    for name, *_ in configs.flat_fields(ppo_tl.PPOTLConfig):
        assert hasattr(args, f"cfg_{name}"), name


def test_help_lists_every_option(runner, capsys):
    """--help renders (a '%' in a field's docs, e.g. PNC's "last 5%", must not break argparse's formatting)."""
    with pytest.raises(SystemExit) as exit_:
        runner.parse_args(["--help"])
    assert exit_.value.code == 0
    text = capsys.readouterr().out
    for cls in (methods.config_class(m) for m in methods.METHODS):
        for name, *_ in configs.flat_fields(cls):
            assert "--" + name.replace("_", "-") in text, name
    # Where a family's calibrated settings replace a default, the help says so.
    assert "ant_dir: 0.001" in " ".join(text.split()), "the MuJoCo families' outer learning rate"
    # and where a method has its own calibration on a family (GMPS's RL step on Point Goal), even at the default.
    assert "point_goal (gmps.ppo): 0.003" in " ".join(text.split())
    assert "point_goal (gmps.ppo): 1.0" in " ".join(text.split())
    assert "every family (gmps.ppo): vanilla" in " ".join(text.split()), "a method's settings on every family"


def test_options_build_the_config(runner):
    described = runner.description_of(["--learning-rate", "0.005", "--hidden-sizes", "64", "32", "--budget", "7",
                                       "--reset-optimizer", "false", "--out", "/nonexistent/x"])
    config = described.methods["ppo_tl"]
    assert config == ppo_tl.PPOTLConfig(ppo=methods.with_family_settings(ppo.PPOConfig(
        learning_rate=0.005, hidden_sizes=(64, 32), budget=7), "point_goal"), reset_optimizer=False)


def test_defaults_are_the_family_defaults(runner):
    for family in ("point_goal", "ant_goal"):
        described = runner.description_of(["--family", family, "--out", "/nonexistent/x"])
        for name, config in described.methods.items():
            expected = methods.default_config(name, family)
            if hasattr(expected, "max_tasks"):  # the runner keeps one experience slot per task
                expected = dataclasses.replace(expected, max_tasks=described.run.num_tasks)
            assert config == methods.with_followed(expected, family), name  # with what follows filled


def test_options_override_the_family_defaults(runner):
    field, value = next(iter(envs.settings("ant_goal", "ppo").items()))
    other = not value if isinstance(value, bool) else value * 2
    flag = "--" + field.replace("_", "-")
    described = runner.description_of(["--family", "ant_goal", flag, str(other).lower(), "--out", "/nonexistent/x"])
    assert getattr(described.methods["ppo_tl"].ppo, field) == other
    for other_field, default in envs.settings("ant_goal", "ppo").items():
        if other_field != field:
            assert getattr(described.methods["ppo_tl"].ppo, other_field) == default


def test_ci_runs_the_readme_test_command():
    readme = (ROOT / "README.md").read_text().splitlines()
    block = readme[readme.index("```bash") + 1: readme.index("```bash") + 3]
    assert "experiments/run_sequence.py" in block[0] and "pytest" in block[1]
    assert block[1] in (ROOT / ".ci" / "run").read_text()


def test_the_readme_describes_every_shipped_method_and_family():
    readme = (ROOT / "README.md").read_text()
    # what jcomps ships (the registries' names may hold more: docs/extending.md's test registers its examples)
    for heading, names in (("### Methods", methods.METHODS), ("### Families", envs.FAMILIES)):
        lines = readme[readme.index(heading):].splitlines()[1:]
        rows = [line for line in lines[:next(i for i, x in enumerate(lines) if x and not x.startswith("|"))]
                if line.startswith("| `")]
        listed = {n for row in rows for n in re.findall(r"`([a-z0-9_]+)`", row.split("|")[1])}
        assert listed == set(names), heading


def _others(name):
    """A run of ``name`` beside CoMPS (the bug this guards against leaked one method's defaults into another)."""
    return ["comps", name] if name != "comps" else ["comps", "ppo_tl"]


def _registered_default(name, family="point_goal", num_tasks=6):
    expected = methods.default_config(name, family)
    if hasattr(expected, "max_tasks"):  # the runner sets it from --num-tasks
        expected = dataclasses.replace(expected, max_tasks=num_tasks)
    return methods.with_followed(expected, family)  # the fields that follow others, filled as run.json records them


@pytest.mark.parametrize("name", methods.METHODS)
def test_runner_config_is_the_registered_default_fresh_and_on_resume(runner, name, tmp_path):
    described = runner.description_of(["--methods", *_others(name), "--out", str(tmp_path)])
    for method in described.run.methods:
        assert described.methods[method] == _registered_default(method), method
    # On --resume, from the run.json the runner wrote, and from an older run.json whose method entries lack fields
    # (they keep the method's registered default, not its config class's).
    description = described.to_json()
    older = {m: {"max_tasks": 6} if hasattr(described.methods[m], "max_tasks") else {} for m in described.run.methods}
    for stored in (description, {**description, "methods": older}):
        (tmp_path / "run.json").write_text(json.dumps(stored))
        resumed = runner.description_of(["--out", str(tmp_path), "--resume"])
        for method in described.run.methods:
            assert resumed.methods[method] == _registered_default(method), method


@pytest.mark.parametrize("family", ["cheetah_vel", "ant_goal", "ant_dir"])
def test_the_ablation_ladder_removes_one_feature_per_rung(family):
    d = {name: methods.default_config(name, family) for name in methods.METHODS}
    comps = d["comps"]
    assert comps.warm_start and comps.meta.importance_sampling and comps.meta.vtrace_baseline
    assert d["gmps_ppo_is_x2"] == dataclasses.replace(comps, warm_start=False, num_skilled=40)
    assert d["gmps_ppo_is"] == dataclasses.replace(comps, warm_start=False)
    # Without importance weights and V-trace, and nothing else (advantage standardisation is the same on every
    # rung; test_meta checks each adjacent pair).
    no_is = dataclasses.replace(comps.meta, importance_sampling=False, vtrace_baseline=False)
    assert d["gmps_ppo"] == dataclasses.replace(comps, warm_start=False, meta=no_is)
    # GMPS's RL step is vanilla policy gradient on every family: one full-batch step, no ratio, whatever the
    # family's calibrated number of PPO steps.
    assert d["gmps"] == dataclasses.replace(d["gmps_ppo"], ppo=dataclasses.replace(
        comps.ppo, num_updates=1, minibatch_size=0, surrogate="vanilla"))
    assert comps.ppo.num_updates == envs.settings(family, "ppo")["num_updates"]
    # The rungs without FTML meta-train from a fresh initialisation; their `_last` variants from the last meta
    # policy, and differ in nothing else.
    assert d["gmps_ppo"].meta_start == d["gmps_ppo_is"].meta_start == "fresh"
    assert d["gmps_ppo_last"] == dataclasses.replace(d["gmps_ppo"], meta_start="last")
    assert d["gmps_ppo_is_last"] == dataclasses.replace(d["gmps_ppo_is"], meta_start="last")
    # The meta step's grid-chosen outer learning rate is a setting of the MuJoCo families, so every rung has it.
    assert {d[name].meta.outer_learning_rate for name in d if name.startswith(("gmps", "comps"))} \
        == {envs.settings(family, "meta")["outer_learning_rate"]} == {0.001}


def test_set_changes_one_method_and_is_recorded(runner, tmp_path):
    argv = ["--methods", "comps", "gmps_ppo_is", "--set", "gmps_ppo_is.meta.inner_learning_rate=0.01",
            "--set", "gmps_ppo_is.ppo.hidden_sizes=64x32", "--inner-learning-rate", "0.002", "--out", str(tmp_path)]
    described = runner.description_of(argv)
    assert described.methods["comps"].meta.inner_learning_rate == 0.002  # the shared option
    assert described.methods["gmps_ppo_is"].meta.inner_learning_rate == 0.01  # --set wins for its method
    assert described.methods["gmps_ppo_is"].ppo.hidden_sizes == (64, 32)
    assert described.methods["comps"].ppo.hidden_sizes == ppo.PPOConfig().hidden_sizes
    description = described.to_json()
    assert description["overrides"] == {"gmps_ppo_is": {"meta.inner_learning_rate": 0.01,
                                                        "ppo.hidden_sizes": [64, 32]}}
    (tmp_path / "run.json").write_text(json.dumps(description))
    resumed = runner.description_of(["--out", str(tmp_path), "--resume"])
    assert resumed.methods == described.methods and resumed.overrides == description["overrides"]


def test_a_different_set_on_resume_is_refused(runner, tmp_path, capsys):
    described = runner.description_of(["--methods", "comps", "--set", "comps.meta.inner_learning_rate=0.01",
                                       "--out", str(tmp_path)])
    rundir.open_run_dir(str(tmp_path), described, resume=False)
    with pytest.raises(SystemExit) as exit_:
        runner.main(["--out", str(tmp_path), "--resume", "--set", "comps.meta.inner_learning_rate=0.02"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "inner_learning_rate: run has 0.01, asked 0.02" in err


@pytest.mark.parametrize("spec,message", [
    ("nope.ppo.budget=3", "method 'nope' is not in this run; its methods: comps, ppo_tl"),
    ("comps.meta=1", "meta is a group of fields; name one: meta.{outer_learning_rate,"),
    ("comps.meta.foo=1", "unknown field 'foo'; allowed: outer_learning_rate"),
    ("comps.meta.inner_learning_rate=-1", "--set comps.meta.inner_learning_rate: invalid config value"),
    ("comps.meta.outer_update=average", "allowed: mean, sequential"),
    ("ppo_tl.ppo.budget=x", "--set ppo_tl.ppo.budget: cannot parse 'x'"),
    ("ppo_tl.budget=3", "unknown field 'budget'; allowed: ppo, reset_optimizer"),
    ("comps", "expected METHOD.FIELD[.FIELD]=VALUE"),
])
def test_bad_set_exits_2_naming_it(runner, spec, message, capsys):
    with pytest.raises(SystemExit) as exit_:
        runner.description_of(["--set", spec, "--out", "/nonexistent/x"])
    assert exit_.value.code == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("family,tasks,values,names", [
    ("point_goal", ["10.0", "-45.5", "12.50"], [10.0, -45.5, 12.5], ("10", "-45.5", "12.5")),
    ("metaworld", ["P-3", "H-11", "102"], [3.0, 211.0, 102.0], ("P-3", "H-11", "B-2")),
])
def test_tasks_option_takes_the_familys_own_terms(runner, family, tasks, values, names, capsys):
    """Tasks are read in the family's terms and kept by canonical name (one run however they were written)."""
    described = runner.description_of(["--family", family, "--tasks", *tasks, "--out", "/nonexistent/x"])
    assert described.run.tasks == names and described.run.num_tasks == len(tasks)
    assert "warning" not in capsys.readouterr().err
    np.testing.assert_array_equal(envs.sequence_values(family, "non-stationary", 0, len(tasks), described.run.tasks),
                                  values)
    # stationary: the chosen tasks shuffled by the seed
    shuffled = [envs.sequence_values(family, "stationary", s, len(tasks), described.run.tasks) for s in range(6)]
    assert all(sorted(s) == sorted(values) for s in shuffled) and len({tuple(s) for s in shuffled}) > 1


def test_a_chosen_held_out_task_is_warned_about(runner, capsys):
    described = runner.description_of(["--family", "metaworld", "--tasks", "P-0", "P-39", "--out", "/nonexistent/x"])
    assert described.run.tasks == ("P-0", "P-39")
    err = capsys.readouterr().err
    assert "warning: --tasks P-39: held out by metaworld" in err and "P-0" not in err


@pytest.mark.parametrize("argv,message", [
    (["--tasks", "abc"], "task 'abc' is not a number"),
    (["--tasks", "720"], "720.0 is out of range"),
    (["--tasks", "10", "20", "--num-tasks", "3"], "num_tasks=3; allowed: the number of tasks given (2;"),
    (["--family", "metaworld", "--tasks", "P-50"], "goal indices are 0-49"),
    (["--family", "metaworld", "--tasks", "Q-3"], "or its name P-k, B-k or H-k"),
    (["--family", "metaworld", "--tasks", "2.5"], "2.5 is not a task"),
])
def test_bad_tasks_exit_2_naming_them(runner, argv, message, capsys):
    with pytest.raises(SystemExit) as info:
        runner.description_of(argv + ["--out", "/nonexistent/x"])
    assert info.value.code == 2 and message in capsys.readouterr().err
