"""Tests of the config-derived command line and the runner's entry point."""

import importlib.util
import json
import pathlib
import re

import pytest

from jcomps import cli, methods, ppo
from jcomps.methods import ppo_tl

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _runner():
    spec = importlib.util.spec_from_file_location("run_sequence", ROOT / "experiments" / "run_sequence.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def runner():
    return _runner()


def test_every_config_field_is_an_option(runner):
    args = runner.parse_args(["--out", "/nonexistent/x"])
    for name, *_ in cli.flat_fields(ppo_tl.PPOTLConfig):
        assert hasattr(args, f"cfg_{name}"), name


def test_options_build_the_config(runner):
    args = runner.parse_args(["--learning-rate", "0.005", "--hidden-sizes", "64", "32", "--budget", "7",
                              "--reset-optimizer", "false", "--out", "/nonexistent/x"])
    config = args.configs["ppo_tl"]
    assert config == ppo_tl.PPOTLConfig(ppo=ppo.PPOConfig(learning_rate=0.005, hidden_sizes=(64, 32), budget=7),
                                        reset_optimizer=False)


def test_defaults_are_the_dataclass_defaults(runner):
    assert runner.parse_args(["--out", "/nonexistent/x"]).configs["ppo_tl"] == ppo_tl.PPOTLConfig()


@pytest.mark.parametrize("argv,message", [
    (["--family", "humanoid"], "invalid choice: 'humanoid'"),
    (["--methods", "maml"], "invalid choice: 'maml'"),
    (["--budget", "0"], "budget=0"),
    (["--budget", "-3"], "budget=-3"),
    (["--learning-rate", "abc"], "invalid"),
    (["--seeds", "0"], "--seeds must be >= 1"),
    (["--num-tasks", "41"], re.escape("--num-tasks must be in [1, 40]")),
    (["--sequence", "shuffled"], "invalid choice: 'shuffled'"),
    (["--methods", "comps", "--num-tasks", "5", "--max-tasks", "3"], "--max-tasks 3 is smaller than --num-tasks 5"),
    (["--methods", "comps", "--inner-learning-rate", "0"], "inner_learning_rate=0.0"),
])
def test_bad_input_exits_2_with_a_message(runner, argv, message, capsys):
    with pytest.raises(SystemExit) as info:
        runner.parse_args(argv + ["--out", "/nonexistent/x"])
    assert info.value.code == 2
    assert re.search(message, capsys.readouterr().err)


def test_runner_writes_results_and_refuses_to_overwrite(runner, tmp_path, capsys):
    out = tmp_path / "run"
    argv = ["--num-tasks", "2", "--seeds", "2", "--budget", "2", "--num-trajectories", "2", "--hidden-sizes", "8",
            "--num-updates", "1", "--minibatch-size", "16", "--out", str(out)]
    runner.main(argv)
    results = json.loads((out / "results.json").read_text())
    assert results["family"] == "point_goal" and results["seeds"] == [0, 1]
    entry = results["methods"]["ppo_tl"]
    assert len(entry["iterations_to_success"]) == 2 and len(entry["iterations_to_success"][0]) == 2
    assert all(isinstance(i, int) and 1 <= i <= 2 for row in entry["iterations_to_success"] for i in row)
    assert "task 2/2" in capsys.readouterr().out
    before = (out / "results.json").read_text()
    with pytest.raises(SystemExit) as info:
        runner.main(argv)
    assert info.value.code == 2 and (out / "results.json").read_text() == before


def test_ci_runs_the_readme_test_command():
    readme = (ROOT / "README.md").read_text().splitlines()
    block = readme[readme.index("```bash") + 1: readme.index("```bash") + 3]
    assert "experiments/run_sequence.py" in block[0] and "pytest" in block[1]
    assert block[1] in (ROOT / ".ci" / "run").read_text()


def test_methods_registry_lists_ppo_tl():
    assert "ppo_tl" in methods.METHODS
