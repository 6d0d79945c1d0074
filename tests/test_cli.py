"""Tests of the config-derived command line and the runner's entry point."""

import dataclasses
import pathlib

from jcomps import cli, methods, ppo
from jcomps.methods import ppo_tl

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_every_config_field_is_an_option(runner):
    args = runner.parse_args(["--out", "/nonexistent/x"])
    for name, *_ in cli.flat_fields(ppo_tl.PPOTLConfig):
        assert hasattr(args, f"cfg_{name}"), name


def test_options_build_the_config(runner):
    args = runner.parse_args(["--learning-rate", "0.005", "--hidden-sizes", "64", "32", "--budget", "7",
                              "--reset-optimizer", "false", "--out", "/nonexistent/x"])
    config = args.configs["ppo_tl"]
    assert config == ppo_tl.PPOTLConfig(ppo=ppo.family_config("point_goal", ppo.PPOConfig(
        learning_rate=0.005, hidden_sizes=(64, 32), budget=7)), reset_optimizer=False)


def test_defaults_are_the_family_defaults(runner):
    for family in ("point_goal", "ant_goal"):
        args = runner.parse_args(["--family", family, "--out", "/nonexistent/x"])
        for name, config in args.configs.items():
            expected = methods.default_config(name, family)
            if hasattr(expected, "max_tasks"):  # the runner keeps one experience slot per task
                expected = dataclasses.replace(expected, max_tasks=args.run.num_tasks)
            assert config == expected, name


def test_options_override_the_family_defaults(runner):
    field, value = next(iter(ppo.FAMILY_DEFAULTS["ant_goal"].items()))
    other = not value if isinstance(value, bool) else value * 2
    flag = "--" + field.replace("_", "-")
    args = runner.parse_args(["--family", "ant_goal", flag, str(other).lower(), "--out", "/nonexistent/x"])
    assert getattr(args.configs["ppo_tl"].ppo, field) == other
    for other_field, default in ppo.FAMILY_DEFAULTS["ant_goal"].items():
        if other_field != field:
            assert getattr(args.configs["ppo_tl"].ppo, other_field) == default


def test_ci_runs_the_readme_test_command():
    readme = (ROOT / "README.md").read_text().splitlines()
    block = readme[readme.index("```bash") + 1: readme.index("```bash") + 3]
    assert "experiments/run_sequence.py" in block[0] and "pytest" in block[1]
    assert block[1] in (ROOT / ".ci" / "run").read_text()


def test_methods_registry_lists_ppo_tl():
    assert "ppo_tl" in methods.METHODS
