"""Tests of the run directory (``jcomps.runner.rundir``): what ``run.json`` holds, a resume compared with it
(differences named, fields added since the run was made filled in or refused), and the runner's exits on a directory it
cannot use."""

import dataclasses
import json
import re
import shutil

import pytest

from jcomps import continual, methods, migrations
from jcomps.methods import comps
from jcomps.runner import description, grid, rundir
from jcomps.runner.files import RunError


def test_differences_name_every_leaf_that_differs():
    stored = {"run": {"seeds": 2, "family": "point_goal"}, "devices": 2, "methods": {"comps": {"ppo": {"lr": 0.1}}}}
    asked = {"run": {"seeds": 3, "family": "point_goal"}, "devices": 2,
             "methods": {"comps": {"ppo": {"lr": 0.1, "added": 1}}}}
    assert rundir.differences(stored, asked) == ["methods.comps.ppo.added: run has None, asked 1",
                                                 "run.seeds: run has 2, asked 3"]
    assert rundir.differences(stored, json.loads(json.dumps(stored))) == []
    assert rundir.differences({"a": [1, 2]}, {"a": {"b": 1}}) == ["a: run has [1, 2], asked {'b': 1}"]


def test_a_run_directory_resumes_with_its_own_description_only(tmp_path):
    run = description.RunConfig(methods=("ppo_tl",), seeds=2)
    configs = {"ppo_tl": methods.default_config("ppo_tl", run.family)}
    described = description.describe(run, continual.EvalConfig(), configs)
    out = tmp_path / "run"
    rundir.open_run_dir(str(out), described, resume=False)
    before = (out / "run.json").read_text()
    assert json.loads(before) == described.to_json()
    assert rundir.read(str(out)) == described  # the one reader gives back what the writer wrote
    rundir.open_run_dir(str(out), described, resume=True)
    assert (out / "run.json").read_text() == before
    other = description.describe(dataclasses.replace(run, seeds=3), continual.EvalConfig(), configs)
    with pytest.raises(RunError, match="was made with another config: run.seeds: run has 2, asked 3"):
        rundir.open_run_dir(str(out), other, resume=True)
    with pytest.raises(RunError, match="already holds a run"):
        rundir.open_run_dir(str(out), described, resume=False)
    assert (out / "run.json").read_text() == before


def test_every_method_config_survives_the_round_trip():
    """``from_json(to_json(d)) == d`` with every method, a grid, overrides and chosen tasks: run.json loses nothing."""
    run = description.RunConfig(family="ant_goal", methods=methods.METHODS, seeds=3, num_tasks=2, tasks=("10", "20"))
    configs = {m: methods.default_config(m, run.family) for m in run.methods}
    configs["comps"] = dataclasses.replace(configs["comps"], ppo=dataclasses.replace(configs["comps"].ppo,
                                                                                      hidden_sizes=(8, 4)))
    axes = (grid.Axis("learning_rate", (0.01, 0.001)), grid.Axis("hidden_sizes", ((8,), (4, 4))))
    described = description.describe(run, continual.EvalConfig(heldout_iterations=2), configs, axes,
                                     {"comps": {"ppo.hidden_sizes": (8, 4)}})
    back = description.from_json(json.loads(json.dumps(described.to_json())))
    assert back == described and back.to_json() == described.to_json()
    assert back.filled == () and back.unresumable is None
    assert back.eval.heldout_budget == 0  # resolved for the family when described (the Ants' default)
    assert [key for m, key, _ in back.entries() if m == "comps"][:2] == ["comps[learning_rate=0.01,hidden_sizes=8]",
                                                                         "comps[learning_rate=0.01,hidden_sizes=4x4]"]


def test_run_json_records_the_values_that_follow_others():
    """Fields that follow another value when None are filled once, when the run is resolved, so that run.json holds
    what ran; one that follows a grid axis stays None and takes each point's value (``comps.meta_config``)."""
    described = description.resolve({"methods": ("comps", "pearl"), "learning_rate": 3e-4})
    comps_config, family = described.methods["comps"], described.family
    assert comps_config.ppo.budget == family.default_budget and comps_config.meta.value_learning_rate == 3e-4
    assert comps_config.meta.reward_scale == comps_config.ppo.reward_scale
    assert comps_config.meta.hold_std is (comps_config.ppo.std_mode == "fixed")
    pearl = described.methods["pearl"]
    assert pearl.budget == family.default_budget and pearl.num_updates == pearl.updates_for(family) >= 1
    assert described.eval.heldout_budget is not None
    assert rundir.differences(described.to_json(), description.from_json(described.to_json()).to_json()) == []
    # Given, a value is kept: it does not follow.
    given = description.resolve({"methods": ("comps",)}, set_specs=["comps.meta.value_learning_rate=0.02"])
    assert given.methods["comps"].meta.value_learning_rate == 0.02
    # Under a grid over the learning rate, the value head's rate follows each point's.
    gridded = description.resolve({"methods": ("comps",)}, grid_specs=["learning_rate=1e-3,3e-4"])
    assert gridded.methods["comps"].meta.value_learning_rate is None
    assert gridded.methods["comps"].ppo.budget == family.default_budget  # follows the family, not the grid
    rates = [comps.meta_config(point.config).value_learning_rate
             for point in grid.points("comps", gridded.methods["comps"], gridded.grid)]
    assert rates == [1e-3, 3e-4]


def test_a_resume_resolves_as_the_new_run_did():
    """One resolver: a resume's description, from the recorded run and the options given again, is the one the run
    was made with, ``--set`` and a grid included."""
    options = {"methods": ("comps", "ppo_tl"), "seeds": 2, "num_tasks": 3, "learning_rate": 1e-3}
    made = description.resolve(options, set_specs=["comps.meta.num_meta_steps=3"], grid_specs=["init_std=0.3,0.5"])
    stored = description.from_json(json.loads(json.dumps(made.to_json())))
    assert description.resolve({}, stored=stored) == made
    assert description.resolve(options, stored=stored) == made
    other = description.resolve({"seeds": 3}, stored=stored)
    assert rundir.differences(made.to_json(), other.to_json()) == ["run.seeds: run has 2, asked 3"]


@pytest.mark.parametrize("edit,message", [
    (lambda d: d.pop("run"), "'run' is missing"),
    (lambda d: d["run"].update(family="nope"), "run: invalid config value family='nope'"),
    (lambda d: d["run"].update(methods=["comps", "nope"]), "invalid config value methods='nope'"),
    (lambda d: d["methods"].pop("comps"), "methods.comps is missing"),
    (lambda d: d["methods"]["comps"]["ppo"].update(learning_rate=-1.0), "methods.comps: invalid config value"),
    (lambda d: d["eval"].update(learnt_eval="sometimes"), "eval: invalid config value learnt_eval"),
    (lambda d: d.update(devices="two"), "devices is 'two'"),
    (lambda d: d.update(format=99), "format 99 is not one this version of jcomps reads"),
])
def test_a_description_that_cannot_be_read_names_the_file_and_field(edit, message):
    run = description.RunConfig(methods=("comps", "ppo_tl"))
    data = description.describe(run, continual.EvalConfig(),
                                {m: methods.default_config(m, run.family) for m in run.methods}).to_json()
    edit(data)
    with pytest.raises(RunError, match=re.escape(message)) as info:
        description.from_json(data, "/runs/x/run.json")
    assert str(info.value).startswith("/runs/x/run.json: ")


def test_run_directory_errors_exit_2_and_keep_earlier_results(runner, full_run, full_run_argv, tmp_path, capsys):
    before = (full_run / "results.json").read_text()
    # An output directory that holds another run.
    with pytest.raises(SystemExit) as info:
        runner.main(full_run_argv + ["--out", str(full_run)])
    assert info.value.code == 2 and "already holds a run" in capsys.readouterr().err
    # --resume with another config names the difference.
    with pytest.raises(SystemExit) as info:
        runner.main(["--out", str(full_run), "--resume", "--learning-rate", "0.01"])
    assert info.value.code == 2 and "learning_rate" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        runner.main(["--out", str(full_run), "--resume", "--seeds", "3"])
    assert info.value.code == 2 and "seeds" in capsys.readouterr().err
    # An impossible or unwritable --out.
    for bad in ("/proc/x", str(full_run / "results.json" / "inside")):
        with pytest.raises(SystemExit) as info:
            runner.main(full_run_argv + ["--out", bad])
        assert info.value.code == 2 and f"--out {bad}: cannot create the run directory" in capsys.readouterr().err
    # --resume of a directory that does not exist.
    with pytest.raises(SystemExit) as info:
        runner.main(["--out", str(tmp_path / "missing"), "--resume"])
    assert info.value.code == 2 and "holds no run" in capsys.readouterr().err
    assert (full_run / "results.json").read_text() == before


@pytest.fixture
def old_run(full_run, tmp_path):
    """``copy(name, edit)``: a copy of ``full_run`` whose run.json ``edit(stored)`` changed in place, as an earlier
    version or a hand would have written it: (its directory, the edited content)."""
    def copy(name: str, edit, checkpoints: bool = True):
        old = tmp_path / name
        shutil.copytree(full_run, old, ignore=None if checkpoints else shutil.ignore_patterns("checkpoints"))
        stored = json.loads((old / "run.json").read_text())
        edit(stored)
        (old / "run.json").write_text(json.dumps(stored))
        return old, stored

    return copy


def _resumed(runner, old, capsys, *options) -> tuple:
    """(exit code, stderr) of ``--resume`` of ``old`` with ``options``."""
    with pytest.raises(SystemExit) as info:
        runner.main(["--out", str(old), "--resume", *options])
    return info.value.code, capsys.readouterr().err


def test_resume_fills_config_fields_added_since_the_run_was_made(runner, full_run, old_run, capsys):
    def edit(stored):  # as if made before these fields existed
        del stored["methods"]["comps"]["ppo"]["entropy_coef"]
        del stored["methods"]["comps"]["warm_start"]
        del stored["run"]["tasks"]  # made before --tasks: the family's list
        del stored["processes"]  # made before runs spread over processes
        # Made before the resolver recorded the values that follow others: null, resolved where used (this run
        # gave --budget and --heldout-budget; its meta step followed its RL step).
        stored["methods"]["comps"]["meta"].update(value_learning_rate=None, reward_scale=None, hold_std=None)

    old, stored = old_run("old", edit)
    filled = rundir.read(str(old)).filled
    assert set(filled) == {"methods.comps.ppo.entropy_coef", "methods.comps.warm_start", "run.tasks", "processes",
                           "methods.comps.meta.value_learning_rate", "methods.comps.meta.reward_scale",
                           "methods.comps.meta.hold_std"}
    # A value other than the field's default is a difference, named, and nothing is written.
    code, err = _resumed(runner, old, capsys, "--set", "comps.ppo.entropy_coef=0.5")
    assert code == 2 and "methods.comps.ppo.entropy_coef: run has 0.0, asked 0.5" in err
    assert json.loads((old / "run.json").read_text()) == stored
    # The default is what the run had: accepted, and recorded.
    runner.main(["--out", str(old), "--resume"])
    assert "already finished" in capsys.readouterr().out
    assert json.loads((old / "run.json").read_text()) == json.loads((full_run / "run.json").read_text())


# As made before issue 27 (its state no longer fits) and before issue 43 (its metrics lack the inner step's gain).
@pytest.mark.parametrize("field", ["value_init", "outer_loss"])
def test_resume_refuses_a_comps_run_whose_checkpoints_no_longer_fit(runner, old_run, capsys, field):
    old, _ = old_run(f"old_{field}", lambda stored: stored["methods"]["comps"]["meta"].pop(field))
    code, err = _resumed(runner, old, capsys)
    assert code == 2 and field in err and "start it anew" in err
    assert rundir.read(str(old)).unresumable is not None  # and still reportable


def test_resume_refuses_a_run_made_before_the_learnt_tasks_evaluations(runner, old_run, capsys):
    def edit(stored):
        for key in ("learnt_eval", "learnt_episodes"):  # as made before issue 28: its checkpoints lack these metrics
            del stored["eval"][key]

    old, _ = old_run("old_eval", edit)
    code, err = _resumed(runner, old, capsys)
    assert code == 2 and "eval.learnt_eval" in err and "start it anew" in err
    assert not (old / "checkpoints" / "comps-unreadable").exists()  # refused before any checkpoint was read


def test_resume_refuses_a_run_made_before_the_checkpoints_format(runner, old_run, capsys):
    def edit(stored):
        assert stored["format"] == migrations.FORMAT
        del stored["format"]  # as made before issue 44: its checkpoints lack the critic's explained variance

    old, _ = old_run("old_format", edit)
    code, err = _resumed(runner, old, capsys)
    assert code == 2 and "explained variance" in err and "start it anew" in err
    assert not (old / "checkpoints" / "comps-unreadable").exists()  # refused before any checkpoint was read


@pytest.mark.parametrize("content", ["{\"run\": {\"family\": \"point_go", "[1, 2]", "\udcff", "{\"run\": 3}"])
def test_a_corrupt_run_json_is_named_by_the_report_and_the_resume(runner, report_script, full_run, tmp_path, capsys,
                                                                  content):
    """A truncated, foreign, undecodable or incomplete run.json: exit code 2 and a message naming the file, no
    traceback."""
    bad = tmp_path / "bad"
    shutil.copytree(full_run, bad, ignore=shutil.ignore_patterns("checkpoints"))
    (bad / "run.json").write_bytes(content.encode("utf-8", "surrogateescape"))
    for main, argv in ((runner.main, ["--out", str(bad), "--resume"]), (report_script.main, [str(bad)])):
        with pytest.raises(SystemExit) as info:
            main(argv)
        err = capsys.readouterr().err
        assert info.value.code == 2 and str(bad / "run.json") in err and "Traceback" not in err


def test_a_run_config_holds_tasks_by_their_canonical_names():
    assert description.canonical_tasks("point_goal", ["10.0", "-45.50"]) == ("10", "-45.5")
    assert description.RunConfig(num_tasks=2, tasks=("10", "-45.5")).tasks == ("10", "-45.5")
    with pytest.raises(ValueError, match=r"tasks=\('10.0', '-45.50'\); allowed: the tasks by their canonical names "
                                         r"\(10, -45.5"):
        description.RunConfig(num_tasks=2, tasks=("10.0", "-45.50"))
