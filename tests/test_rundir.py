"""Tests of the run directory (``jcomps.runner.rundir``): what ``run.json`` holds, a resume compared with it
(differences named, fields added since the run was made filled in or refused), and the runner's exits on a directory it
cannot use."""

import dataclasses
import json
import shutil

import pytest

from jcomps import continual, methods
from jcomps.runner import experiment, rundir
from jcomps.runner.checkpoint import RunError


def test_differences_name_every_leaf_that_differs():
    stored = {"run": {"seeds": 2, "family": "point_goal"}, "devices": 2, "methods": {"comps": {"ppo": {"lr": 0.1}}}}
    asked = {"run": {"seeds": 3, "family": "point_goal"}, "devices": 2,
             "methods": {"comps": {"ppo": {"lr": 0.1, "added": 1}}}}
    assert rundir.differences(stored, asked) == ["methods.comps.ppo.added: run has None, asked 1",
                                                 "run.seeds: run has 2, asked 3"]
    assert rundir.differences(stored, json.loads(json.dumps(stored))) == []
    assert rundir.differences({"a": [1, 2]}, {"a": {"b": 1}}) == ["a: run has [1, 2], asked {'b': 1}"]


def test_a_run_directory_resumes_with_its_own_description_only(tmp_path):
    run = experiment.RunConfig(methods=("ppo_tl",), seeds=2)
    configs = {"ppo_tl": methods.default_config("ppo_tl", run.family)}
    description = rundir.describe(run, continual.EvalConfig(), configs)
    out = tmp_path / "run"
    rundir.open_run_dir(str(out), description, resume=False)
    before = (out / "run.json").read_text()
    assert json.loads(before) == description
    rundir.open_run_dir(str(out), description, resume=True)
    assert (out / "run.json").read_text() == before
    other = rundir.describe(dataclasses.replace(run, seeds=3), continual.EvalConfig(), configs)
    with pytest.raises(RunError, match="was made with another config: run.seeds: run has 2, asked 3"):
        rundir.open_run_dir(str(out), other, resume=True)
    with pytest.raises(RunError, match="already holds a run"):
        rundir.open_run_dir(str(out), description, resume=False)
    assert (out / "run.json").read_text() == before


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


def test_resume_fills_config_fields_added_since_the_run_was_made(runner, full_run, tmp_path, capsys):
    old = tmp_path / "old"
    shutil.copytree(full_run, old)
    run_json = old / "run.json"
    stored = json.loads(run_json.read_text())
    del stored["methods"]["comps"]["ppo"]["entropy_coef"]  # as if made before these fields existed
    del stored["methods"]["comps"]["warm_start"]
    del stored["run"]["tasks"]  # made before --tasks: the family's list
    run_json.write_text(json.dumps(stored))
    # A value other than the field's default is a difference, named, and nothing is written.
    with pytest.raises(SystemExit) as info:
        runner.main(["--out", str(old), "--resume", "--set", "comps.ppo.entropy_coef=0.5"])
    assert info.value.code == 2 and "entropy_coef" in capsys.readouterr().err
    assert json.loads(run_json.read_text()) == stored
    # The default is what the run had: accepted, and recorded.
    runner.main(["--out", str(old), "--resume"])
    assert "already finished" in capsys.readouterr().out
    assert json.loads(run_json.read_text()) == json.loads((full_run / "run.json").read_text())


def _refused_resume(runner, full_run, tmp_path, capsys, name: str, edit) -> tuple:
    """A copy of ``full_run`` whose run.json ``edit(stored)`` changes in place, resumed: (its directory, the exit
    code, stderr)."""
    old = tmp_path / name
    shutil.copytree(full_run, old)
    run_json = old / "run.json"
    stored = json.loads(run_json.read_text())
    edit(stored)
    run_json.write_text(json.dumps(stored))
    with pytest.raises(SystemExit) as info:
        runner.main(["--out", str(old), "--resume"])
    return old, info.value.code, capsys.readouterr().err


# As made before issue 27 (its state no longer fits) and before issue 43 (its metrics lack the inner step's gain).
@pytest.mark.parametrize("field", ["value_init", "outer_loss"])
def test_resume_refuses_a_comps_run_whose_checkpoints_no_longer_fit(runner, full_run, tmp_path, capsys, field):
    _, code, err = _refused_resume(runner, full_run, tmp_path, capsys, f"old_{field}",
                                   lambda stored: stored["methods"]["comps"]["meta"].pop(field))
    assert code == 2 and field in err and "start it anew" in err


def test_resume_refuses_a_run_made_before_the_learnt_tasks_evaluations(runner, full_run, tmp_path, capsys):
    def edit(stored):
        for key in ("learnt_eval", "learnt_episodes"):  # as made before issue 28: its checkpoints lack these metrics
            del stored["eval"][key]

    old, code, err = _refused_resume(runner, full_run, tmp_path, capsys, "old_eval", edit)
    assert code == 2 and "eval.learnt_eval" in err and "start it anew" in err
    assert not (old / "checkpoints" / "comps-unreadable").exists()  # refused before any checkpoint was read


def test_resume_refuses_a_run_made_before_the_checkpoints_format(runner, full_run, tmp_path, capsys):
    def edit(stored):
        assert stored["format"] == rundir.FORMAT
        del stored["format"]  # as made before issue 44: its checkpoints lack the critic's explained variance

    old, code, err = _refused_resume(runner, full_run, tmp_path, capsys, "old_format", edit)
    assert code == 2 and "explained variance" in err and "start it anew" in err
    assert not (old / "checkpoints" / "comps-unreadable").exists()  # refused before any checkpoint was read


@pytest.mark.parametrize("content", ["{\"run\": {\"family\": \"point_go", "[1, 2]", "\udcff"])
def test_a_corrupt_run_json_is_named_by_the_report_and_the_resume(runner, report_script, full_run, tmp_path, capsys,
                                                                  content):
    """A truncated, foreign or undecodable run.json: exit code 2 and a message naming the file, no traceback."""
    bad = tmp_path / "bad"
    shutil.copytree(full_run, bad, ignore=shutil.ignore_patterns("checkpoints"))
    (bad / "run.json").write_bytes(content.encode("utf-8", "surrogateescape"))
    for main, argv in ((runner.main, ["--out", str(bad), "--resume"]), (report_script.main, [str(bad)])):
        with pytest.raises(SystemExit) as info:
            main(argv)
        err = capsys.readouterr().err
        assert info.value.code == 2 and str(bad / "run.json") in err and "Traceback" not in err
