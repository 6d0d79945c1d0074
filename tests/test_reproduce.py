"""Tests of the paper's experiments reproduced (``jcomps.analysis.reproduction``, ``jcomps.analysis.paper``,
``experiments/reproduce.py``): protocols, the tables beside the paper's, and a tiny study run, resumed and reported
partially, each method a ``run_sequence.py`` process of its own."""

import json
import os
import shutil

import numpy as np
import pytest

from jcomps.analysis import paper, reproduction, statistics
from jcomps.runner import results

# --- protocols ---------------------------------------------------------------------------------------------------

def test_the_scales():
    cpu = reproduction.protocol("ant_goal")
    assert (cpu.scale, cpu.sequences, cpu.methods, cpu.seeds, cpu.num_tasks, cpu.heldout_iterations) == (
        "cpu", ("non-stationary",), ("comps", "gmps_ppo", "gmps_ppo_is", "ppo_tl"), 4, 6, 0)
    full = reproduction.protocol("metaworld", "paper", ablation=True)
    assert full.sequences == ("stationary", "non-stationary") and full.seeds == 6 and full.heldout_iterations == 5
    assert full.num_tasks == 39  # MetaWorld's list; 40 elsewhere
    assert reproduction.protocol("ant_dir", "paper").num_tasks == 40
    assert full.methods == ("comps", "ppo_tl", "gmps_ppo", "maml_tl", "pnc", "pearl", "gmps", "gmps_ppo_is",
                            "gmps_ppo_is_x2")
    mine = reproduction.protocol("ant_goal", seeds=3, num_tasks=2, methods_=["ppo_tl", "comps"], extra=("--x",))
    assert mine.methods == ("comps", "ppo_tl") and mine.seeds == 3 and mine.runs() == [
        ("non-stationary", "comps"), ("non-stationary", "ppo_tl")]
    assert mine.run_options("non-stationary", "ppo_tl")[-1] == "--x"
    assert reproduction.Protocol.from_json(json.loads(json.dumps(mine.to_json()))) == mine


@pytest.mark.parametrize("change, field", [
    (dict(family="hopper"), "family"), (dict(scale="gpu"), "scale"), (dict(seeds=1), "seeds"),
    (dict(num_tasks=41), "num_tasks"), (dict(methods=("ppo_tl",)), "methods"), (dict(methods=("comps", "sac")),
                                                                                  "methods"),
    (dict(sequences=("shuffled",)), "sequences")])
def test_bad_protocols_name_the_field(change, field):
    with pytest.raises(ValueError, match=f"invalid config value {field}="):
        reproduction.Protocol(**{"family": "ant_goal", **change})


# --- the tables --------------------------------------------------------------------------------------------------

def _results(iterations: dict, returns: dict, backward=None) -> dict:
    """A merged results.json's methods: iterations [S, N] and average returns [S, N] per method."""
    out = {"description": {"run": {"family": "ant_goal"}}, "methods": {}}
    for name, its in iterations.items():
        its = np.asarray(its, float)
        bt = backward if backward is not None and name == "comps" else np.full(its.shape, np.nan)
        out["methods"][name] = {
            "iterations_to_success": its.tolist(), "mean_return_per_task": np.asarray(returns[name]).tolist(),
            "backward_transfer": [[None if np.isnan(v) else v for v in row] for row in np.asarray(bt, float)],
            "return_curves": [[[float(r)] * int(i) for i, r in zip(row_i, row_r)]
                              for row_i, row_r in zip(its, np.asarray(returns[name]))]}
    return out


RNG = np.random.default_rng(0)
FAST = np.array([[30, 20, 10, 5]] * 4) + RNG.integers(0, 3, (4, 4))  # comps: faster as tasks accumulate
SLOW = np.array([[60, 70, 80, 90]] * 4) + RNG.integers(0, 3, (4, 4))
SAME = FAST + RNG.integers(-1, 2, (4, 4))


def test_the_p_value_table_tests_the_papers_quantity_beside_its_p_value():
    r = _results({"comps": FAST, "ppo_tl": SLOW, "gmps_ppo": SAME},
                 {"comps": -FAST, "ppo_tl": -SLOW, "gmps_ppo": -SAME})
    rows = {row["method"]: row for row in reproduction.p_value_table(r, "ant_goal", "non-stationary")}
    assert rows["ppo_tl"]["paper_p"] == paper.P_VALUES["non-stationary"]["ant_goal"]["ppo_tl"] == 0.0003071245518
    assert rows["gmps_ppo"]["paper_p"] is None  # not in the paper's tables
    assert rows["ppo_tl"]["quantity"] == "mean_return"  # the non-stationary table tests the average reward
    expected = statistics.significance(FAST.mean(1), SLOW.mean(1))
    assert rows["ppo_tl"]["iterations"]["p_ttest"] == expected["p_ttest"]
    assert rows["ppo_tl"]["iterations"]["mean_a"] == pytest.approx(FAST.mean())
    stationary = reproduction.p_value_table(r, "ant_goal", "stationary")
    assert stationary[0]["quantity"] == "iterations" and stationary[0]["paper_p"] == 4.54e-11


def _verdicts(r, family="ant_goal", sequence="non-stationary"):
    return {row["claim"]: row["verdict"] for row in reproduction.claims_table({sequence: r}, family)}


def test_the_claims_hold_level_or_reverse_with_the_figures():
    backward = np.full(FAST.shape, 0.8)
    ahead = _results({"comps": FAST, "ppo_tl": SLOW, "gmps_ppo": SLOW},
                     {"comps": -FAST, "ppo_tl": -SLOW, "gmps_ppo": -SLOW}, backward)
    every = {"fastest", "faster_with_tasks", "ahead_of_gmps_ppo", "highest_return", "backward_transfer"}
    assert _verdicts(ahead, sequence="stationary") == dict.fromkeys(every, "holds")
    # "the fastest" is said of the stationary sequences only (L562-563; L790: "most tasks").
    assert _verdicts(ahead) == {**dict.fromkeys(every, "holds"), "fastest": "not claimed"}
    behind = _results({"comps": SLOW, "ppo_tl": FAST, "gmps_ppo": FAST},
                      {"comps": -SLOW, "ppo_tl": -FAST, "gmps_ppo": -FAST}, backward - 1.0)
    assert _verdicts(behind, sequence="stationary") == dict.fromkeys(every, "reversed")
    level = _verdicts(_results({"comps": FAST, "gmps_ppo": SAME}, {"comps": -FAST, "gmps_ppo": -SAME}),
                      sequence="stationary")
    assert level["fastest"] == "level" and level["ahead_of_gmps_ppo"] == "level"
    assert level["backward_transfer"] == "n/a"  # not measured
    # MetaWorld: backward transfer not claimed (L849); Point Goal, not in the paper: no row for a claim the paper
    # makes of named families only.
    assert _verdicts(ahead, "metaworld")["backward_transfer"] == "not claimed"
    assert "backward_transfer" not in _verdicts(ahead, "point_goal")


def test_a_clean_separation_is_significant_not_level():
    """Every seed the same: two constant groups apart, the t-test's p is exactly 0, which is significant (a p of 0
    is not a missing one)."""
    fast, slow = np.array([[30, 20, 10, 5]] * 4), np.array([[60, 70, 80, 90]] * 4)
    assert statistics.significance(fast.mean(1), slow.mean(1))["p_ttest"] == 0.0
    every = {"fastest", "faster_with_tasks", "ahead_of_gmps_ppo", "highest_return"}
    ahead = _results({"comps": fast, "ppo_tl": slow, "gmps_ppo": slow},
                     {"comps": -fast, "ppo_tl": -slow, "gmps_ppo": -slow})
    assert {k: v for k, v in _verdicts(ahead, sequence="stationary").items() if k in every} == dict.fromkeys(
        every, "holds")
    behind = _results({"comps": slow, "ppo_tl": fast, "gmps_ppo": fast},
                      {"comps": -slow, "ppo_tl": -fast, "gmps_ppo": -fast})
    assert {k: v for k, v in _verdicts(behind, sequence="stationary").items() if k in every} == dict.fromkeys(
        every, "reversed")
    rows = {row["claim"]: row for row in reproduction.claims_table({"stationary": ahead}, "ant_goal")}
    assert "(p 0)" in rows["fastest"]["shows"]
    assert "paired t-test over seeds, p 0)" in rows["faster_with_tasks"]["shows"]


def test_each_claim_only_where_the_paper_makes_it():
    said = paper.claim
    assert said("fastest", "stationary", "metaworld").made and said("fastest", "stationary", "ant_dir").where == \
        "L562-563"
    not_fastest = said("fastest", "non-stationary", "ant_goal")
    assert not not_fastest.made and "L790" in not_fastest.where and "most tasks" in not_fastest.text
    # "attains higher rewards" on Half-Cheetah (L584); PPO+TL level on MetaWorld and Ant Direction (L812).
    assert said("highest_return", "non-stationary", "cheetah_vel").where == "L584, L812"
    assert said("highest_return", "non-stationary", "ant_goal").made
    for family in ("ant_dir", "metaworld"):
        assert not said("highest_return", "non-stationary", family).made
        assert said("highest_return", "non-stationary", family).where == "L812"
    # GMPS+PPO: L591 is the stationary figure's iterations; the non-stationary rows rest on L782 (returns) and, on
    # MetaWorld, L587 (iterations).
    assert said("ahead_of_gmps_ppo", "stationary", "ant_goal")[2:] == (
        "L591", ("stationary",), (), True, "iterations")
    assert (said("ahead_of_gmps_ppo", "non-stationary", "ant_goal").where,
            said("ahead_of_gmps_ppo", "non-stationary", "ant_goal").quantity) == ("L782", "mean_return")
    assert (said("ahead_of_gmps_ppo", "non-stationary", "metaworld").where,
            said("ahead_of_gmps_ppo", "non-stationary", "metaworld").quantity) == ("L587", "iterations")
    assert said("backward_transfer", "stationary", "point_goal") is None
    assert all(c.quantity in (None, "iterations", "mean_return") for c in paper.CLAIMS)

    # GMPS+PPO solves faster but earns less: behind it on the stationary claim (iterations), ahead on the
    # non-stationary one (returns); the row cites the line it checks.
    r = _results({"comps": SLOW, "gmps_ppo": FAST}, {"comps": -FAST, "gmps_ppo": -SLOW})
    for sequence, where, verdict in (("stationary", "L591", "reversed"), ("non-stationary", "L782", "holds")):
        row = next(row for row in reproduction.claims_table({sequence: r}, "ant_goal")
                   if row["claim"] == "ahead_of_gmps_ppo")
        assert (row["where"], row["verdict"]) == (where, verdict)
    # Where the paper does not make a claim the row says so, and still shows what this study measured.
    row = next(row for row in reproduction.claims_table({"non-stationary": r}, "ant_dir")
               if row["claim"] == "highest_return")
    assert row["verdict"] == "not claimed" and "somewhat similar" in row["text"] and "gmps_ppo" in row["shows"]


def test_the_report_and_its_figures(tmp_path):
    r = _results({"comps": FAST, "ppo_tl": SLOW}, {"comps": -FAST, "ppo_tl": -SLOW})
    proto = reproduction.protocol("ant_goal", methods_=["comps", "ppo_tl"], num_tasks=4)
    text = reproduction.markdown("ant_goal", proto, {"non-stationary": r})
    assert "# Reproducing the paper on ant_goal (the paper's Ant Goal)" in text
    assert "| ppo_tl |" in text and "| 3.1e-04 |" in text  # the paper's p-value beside ours
    assert "| CoMPS \"solves all of the tasks the fastest\" is said of the stationary sequences" in text
    assert "| L562-563, L790 | non-stationary | **not claimed** |" in text
    # The column "ours" and the verdicts are the t-test's, the bootstrap's floor being above most of the paper's p.
    assert "17 of the paper's 32 p-values are below it" in text and "1/30,001 ≈ 3.3e-05" in text
    assert "Ours, not the paper's: the paired t-test" in text and "the threshold 0.5" in text
    stationary = reproduction.markdown("ant_goal", proto, {"stationary": r})
    assert "| CoMPS \"solves all of the tasks the fastest\" | L562-563 | stationary | **holds** |" in stationary
    paths = reproduction.figures({"non-stationary": r, "stationary": r}, str(tmp_path), "point_goal")
    assert [os.path.basename(p) for p in paths] == ["figure3.png", "lifelong_return.png"]
    assert all(os.path.getsize(p) > 0 for p in paths)


# --- a tiny study, end to end ------------------------------------------------------------------------------------

def _tiny_extra(tiny_options):
    """The tiny runner options without the evaluations' (the protocol sets the held-out test)."""
    drop = {"--heldout-iterations", "--heldout-budget"}
    out, skip = [], False
    for a in tiny_options:
        if skip:
            skip = False
        elif a in drop:
            skip = True
        else:
            out.append(a)
    return out


@pytest.fixture(scope="module")
def study(reproduce, tiny_options, tmp_path_factory):
    """CoMPS and PPO+TL on 2 Point Goal tasks, 2 seeds, one device each, every method a process of its own (a
    compile cache shared by the processes); returns (directory, argv)."""
    out = tmp_path_factory.mktemp("study") / "pg"
    os.environ["JCOMPS_COMPILE_CACHE"] = str(tmp_path_factory.mktemp("cache"))
    argv = ["point_goal", "--out", str(out), "--methods", "comps", "ppo_tl", "--num-tasks", "2", "--seeds", "2",
            "--devices", "1", "--", *_tiny_extra(tiny_options)]
    try:
        reproduce.main(argv)
    finally:
        os.environ["JCOMPS_COMPILE_CACHE"] = "none"
    return out, argv


def test_a_study_runs_each_method_and_reports_beside_the_paper(study):
    out, _ = study
    stored = json.loads((out / "study.json").read_text())
    assert stored["protocol"]["methods"] == ["comps", "ppo_tl"] and stored["devices"] == 1
    merged = json.loads((out / "non-stationary" / "merged" / "results.json").read_text())
    assert list(merged["methods"]) == ["comps", "ppo_tl"]
    for method in ("comps", "ppo_tl"):  # each its own run directory, run with the protocol's options
        run = json.loads((out / "non-stationary" / method / "run.json").read_text())
        assert run["run"]["methods"] == [method] and run["run"]["num_tasks"] == 2 and run["devices"] == 1
        assert run["eval"]["heldout_iterations"] == 0 and (out / "logs" / f"non-stationary-{method}.log").is_file()
    rep = json.loads((out / "reproduction.json").read_text())
    assert rep["partial"] is None and rep["figures"] == ["figures/figure3.png", "figures/lifelong_return.png"]
    assert {row["claim"] for row in rep["claims"]} >= {"fastest", "faster_with_tasks", "highest_return"}
    ppo_row = rep["p_values"]["non-stationary"][0]
    its = np.asarray(merged["methods"]["ppo_tl"]["iterations_to_success"], float).mean(1)
    assert ppo_row["method"] == "ppo_tl" and ppo_row["iterations"]["mean_b"] == pytest.approx(its.mean())
    assert "## non-stationary" in (out / "report.md").read_text()


def test_a_study_resumes_what_did_not_finish_and_reports_what_did(study, reproduce, capsys):
    out, argv = study
    copy = out.parent / "copy"
    shutil.copytree(out, copy)
    # PPO+TL "stopped" after its first task: its final results gone, the first task's kept as partial results.
    raw = results.load(str(copy / "non-stationary" / "ppo_tl"), "ppo_tl")
    os.remove(results.path(str(copy / "non-stationary" / "ppo_tl"), "ppo_tl"))
    results.save_partial(str(copy / "non-stationary" / "ppo_tl"), "ppo_tl", results.truncate(raw, 1))
    reproduce.main(["point_goal", "--out", str(copy), "--partial"])
    rep = json.loads((copy / "reproduction.json").read_text())
    assert rep["partial"] == {"non-stationary": {"tasks": 1, "of": 2, "tasks_done": {"comps": 2, "ppo_tl": 1}}}
    assert "**Partial**" in (copy / "report.md").read_text()
    capsys.readouterr()
    reproduce.main(["point_goal", "--out", str(copy), "--resume"])
    said = capsys.readouterr().out
    assert "2 runs (1 finished, 1 to run)" in said and "starting ppo_tl" in said and "starting comps" not in said
    assert json.loads((copy / "reproduction.json").read_text())["partial"] is None
    again = results.load(str(copy / "non-stationary" / "ppo_tl"), "ppo_tl")
    np.testing.assert_array_equal(again.per_task.task.iterations, raw.per_task.task.iterations)


@pytest.mark.parametrize("argv, says", [
    (["hopper"], "argument family|invalid config value family"),
    (["point_goal", "--seeds", "1"], "seeds"),
    (["point_goal", "--parallel", "0"], "--parallel"),
    (["point_goal", "--resume"], "--resume needs --out"),
])
def test_bad_options_exit_2_naming_them(reproduce, argv, says, capsys, tmp_path):
    with pytest.raises(SystemExit) as exit_:
        reproduce.main(argv + ["--out", str(tmp_path / "x")] if "--resume" not in argv else argv)
    assert exit_.value.code == 2
    import re
    assert re.search(says, capsys.readouterr().err)


def test_a_resume_must_match_the_study_and_a_corrupt_study_is_named(study, reproduce, capsys, tmp_path):
    out, _ = study
    with pytest.raises(SystemExit) as exit_:
        reproduce.main(["point_goal", "--out", str(out), "--resume", "--seeds", "3"])
    assert exit_.value.code == 2 and "seeds differ" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        reproduce.main(["point_goal", "--out", str(out)])  # a new study where one is
    assert "already holds a study" in capsys.readouterr().err
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "study.json").write_text("{not json")
    with pytest.raises(SystemExit) as exit_:
        reproduce.main(["point_goal", "--out", str(bad), "--resume"])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and "study.json is not a readable study" in err and "Traceback" not in err


def test_print_commands_creates_the_study_and_prints_each_run(reproduce, capsys, tmp_path):
    out = tmp_path / "slurm"
    reproduce.main(["ant_dir", "--scale", "paper", "--out", str(out), "--print-commands", "--", "--budget", "5"])
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 12  # 6 methods x 2 sequences, none started
    assert lines[0].endswith(f"--family ant_dir --methods comps --sequence stationary --seeds 6 --num-tasks 40 "
                             f"--chunk-tasks 1 --heldout-iterations 5 --budget 5 --out {out}/stationary/comps "
                             f"--devices {json.loads((out / 'study.json').read_text())['devices']}")
    assert all("run_sequence.py" in line and "--resume" not in line for line in lines)


def test_an_interrupted_study_stops_its_runs_and_says_how_to_continue(reproduce, monkeypatch, tmp_path, capsys):
    """Ctrl-C or SIGTERM while a run runs: the run is terminated (its checkpoints stay), none is left behind."""
    import sys

    args = reproduce.parse_args(["point_goal", "--out", str(tmp_path / "s"), "--methods", "comps", "ppo_tl",
                                 "--parallel", "2", "--devices", "1"])
    sleeper = [sys.executable, "-c", "import time; print('running', flush=True); time.sleep(600)"]
    monkeypatch.setattr(reproduce, "command", lambda *_: sleeper)

    def interrupt(_):
        raise KeyboardInterrupt

    monkeypatch.setattr(reproduce.time, "sleep", interrupt)  # the scheduler's first wait: both runs started
    failed = reproduce.run_all(args)
    assert sorted((s, m) for s, m, _ in failed) == [("non-stationary", "comps"), ("non-stationary", "ppo_tl")]
    assert all(code != 0 for *_, code in failed)
    err = capsys.readouterr().err
    assert "2 run(s) interrupted" in err and "--resume` continues them" in err
