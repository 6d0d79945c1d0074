"""Tests of the experiment runner's host loop (``jcomps.runner.experiment``) and the scripts around it: resume equality,
the results schema, checkpoints and the CLI's error paths. The tiny run they share (``full_run``) is in
conftest.py; the run directory, the members, the programs and the console have their own test files."""

import json
import os
import re
import shutil

import jax
import numpy as np
import pytest

from jcomps import continual
from jcomps.analysis import report
from jcomps.runner import checkpoint, events, experiment, results, rundir
from jcomps.runner.files import RunError


def _raw(out, name):
    with np.load(out / "raw" / f"{name}.npz") as f:
        return {k: f[k] for k in f.files if k != "seconds"}


def test_results_schema(full_run):
    results = json.loads((full_run / "results.json").read_text())
    assert results["seeds"] == [0, 1]
    assert results["description"]["run"]["methods"] == ["comps", "ppo_tl"]
    for name in ("comps", "ppo_tl"):
        m = results["methods"][name]
        its = m["iterations_to_success"]
        assert len(its) == 2 and all(len(row) == 3 for row in its)
        assert all(isinstance(i, int) and 1 <= i <= 3 for row in its for i in row)
        assert len(m["iterations_to_success_mean"]) == 3 and len(m["iterations_to_success_se"]) == 3
        assert np.asarray(m["mean_return_per_task"]).shape == (2, 3)
        for curves in (m["return_curves"], m["success_rate_curves"]):
            assert [[len(c) for c in row] for row in curves] == its  # one entry per iteration that ran
        bt = m["backward_transfer"]
        assert np.asarray(bt, dtype=object).shape == (2, 3) and bt[0][0] is None  # no previous task at task 1
        h = m["heldout"]
        assert h["after_tasks"] == [0, 1, 2, 3] and h["adaptation_iterations"] == 1
        assert np.asarray(h["adapted_return"]).shape == (2, 4)
        # Iterations-to-success on each of the 8 held-out tasks, capped at --heldout-budget 3.
        held = np.asarray(h["iterations_to_success"])
        assert h["budget"] == 3 and held.shape == (2, 4, 8) and held.min() >= 1 and held.max() <= 3
        np.testing.assert_array_equal(np.asarray(h["solved"]) | (held == 3), True)
        assert [q["tasks"] for q in m["iqm"]] == [[1, 1], [2, 3]]
        assert all(q["ci"][0] <= q["iqm"] <= q["ci"][1] for q in m["iqm"])
        assert m["devices"] == 2 and m["nonfinite_iterations"] == 0
        # Samples-to-success: 2 episodes of Point Goal's 100 steps per iteration.
        assert m["env_steps_per_iteration"] == 200
        np.testing.assert_allclose(m["env_steps_to_success_mean"], np.asarray(m["iterations_to_success_mean"]) * 200)
        # The field's metrics: forgetting and average performance from the learnt tasks' evaluations after every
        # chunk (of one task), forward transfer only against a ppo run, a performance profile over the budget.
        f, ap = m["forgetting"], m["average_performance"]
        assert f["after_tasks"] == 3 and np.asarray(f["per_task"], dtype=float).shape == (2, 3)
        assert f["by_evaluation"]["after_tasks"] == ap["by_evaluation"]["after_tasks"] == [1, 2, 3]
        assert all(0 <= v <= 1 for row in f["success_when_learnt"] + f["final_success"] for v in row)
        assert ap["after_tasks"] == 3 and len(ap["per_seed"]) == 2 and 0 <= ap["mean"] <= 1
        assert m["learnt_success"]["mean"][0][1:] == [None, None]  # after task 1, tasks 2 and 3 are not learnt
        assert m["forward_transfer"]["reference"] is None and "no ppo" in m["forward_transfer"]["note"]
        profile = m["performance_profile"]
        assert profile["tau"] == [1, 2, 3] and np.all(np.diff(profile["fraction"]) >= 0)
        assert all(lo <= v <= hi for lo, v, hi in zip(profile["ci_low"], profile["fraction"], profile["ci_high"]))
    # The meta step's health, for the method that has one: per seed and task, and per seen slot.
    meta = results["methods"]["comps"]["meta"]
    assert "meta" not in results["methods"]["ppo_tl"]
    for key in ("value_ev_start", "value_ev_end", "newest_value_ev_start", "value_bias_over_return_std_end",
                "value_l2_end", "adv_abs_end", "rho_end", "oldest_rho_end", "bc_loss_end", "inner_gain_start",
                "inner_gain_end", "newest_inner_gain_end"):
        assert np.asarray(meta[key], dtype=float).shape == (2, 3), key
        assert np.all(np.isfinite(np.asarray(meta[key], dtype=float))), key
    assert all(0 < r <= 1 for row in meta["rho_end"] for r in row)
    for key in ("per_slot_value_ev_end", "per_slot_inner_gain_end"):
        assert [[len(slots) for slots in row] for row in meta[key]] == [[1, 2, 3]] * 2, key
    assert len(meta["value_ev_end_mean"]) == 3
    sig = results["significance"]["against"]["ppo_tl"]
    assert sig["bootstrap_samples"] == 30_000 and set(sig) >= {"p_ttest", "p_bootstrap", "t"}
    poi = results["significance"]["probability_of_improvement"]
    assert list(poi) == ["ppo_tl"] and poi["ppo_tl"]["over"] == "comps"
    assert poi["ppo_tl"]["ci"][0] <= poi["ppo_tl"]["probability"] <= poi["ppo_tl"]["ci"][1]
    for plot in ("iterations_to_success", "samples_to_success", "lifelong_return", "per_task_return",
                 "backward_transfer", "heldout_meta_test", "meta_health", "performance_profile", "continual_metrics"):
        assert (full_run / "plots" / f"{plot}.png").stat().st_size > 1000
    table = (full_run / "significance.md").read_text()
    assert table.startswith("Statistic") and "| comps vs |" in table and "Interquartile mean (IQM)" in table
    assert "| method | average performance | forgetting | forward transfer vs ppo | P(fewer iterations than comps) |" \
        in table
    assert results["significance"]["baseline"] == "comps"


def test_learnt_tasks_are_evaluated_with_the_episodes_they_had_when_learnt(full_run):
    """After every chunk (one task here) the policy is evaluated on every task learnt: on the task just learnt it
    is the policy that ``evaluate_task`` evaluated right after learning it, on the same episodes (another compiled
    program, the same numbers), so that task's forgetting is 0."""
    for name in ("comps", "ppo_tl"):
        raw = results.load(str(full_run), name)
        learnt, later = raw.per_task.learnt, raw.measured.learnt
        assert learnt.valid.all() and later.success_rate.shape == (2, 4, 3)  # [seeds, after 0-3 tasks, tasks]
        np.testing.assert_array_equal(later.valid[0], np.tril(np.ones((4, 3), bool), -1))  # learnt by then
        for p in (1, 2, 3):
            np.testing.assert_allclose(later.mean_return[:, p, p - 1], learnt.mean_return[:, p - 1], rtol=1e-5)
            np.testing.assert_allclose(later.success_rate[:, p, p - 1], learnt.success_rate[:, p - 1], atol=1e-6)
        assert raw.per_task.backward_success.shape == raw.per_task.backward_returns.shape == (2, 3, 2)


def test_killed_and_resumed_run_equals_the_uninterrupted_one(runner, full_run, full_run_argv, tmp_path,
                                                             kill_and_resume):
    # "Kill" comps after its first chunk (its checkpoint 1 exists, nothing else); ppo_tl runs on the resume.
    kill_and_resume(runner, full_run_argv, tmp_path / "killed", ["comps"], full_run)


def test_unreadable_checkpoint_falls_back_to_the_one_before(runner, full_run, full_run_argv, tmp_path):
    out = tmp_path / "corrupt"
    described = runner.description_of(full_run_argv + ["--out", str(out)])
    rundir.open_run_dir(str(out), described, resume=False)
    experiment.run_method(str(out), "ppo_tl", described, resume=False,
                          programs=runner.PROGRAMS, stop_after_chunks=2)
    for path in (out / "checkpoints" / "ppo_tl" / "2").rglob("*"):
        if path.is_file():
            path.write_bytes(b"garbage")
    shown = []
    experiment.run_method(str(out), "ppo_tl", described, resume=True,
                          progress_fn=shown.append, programs=runner.PROGRAMS)
    assert any(isinstance(e, events.Warned) and "cannot be read" in e.message for e in shown)
    assert any(isinstance(e, events.Resumed) and e.step == 1 for e in shown)
    a, b = _raw(full_run, "ppo_tl"), _raw(out, "ppo_tl")
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_no_readable_checkpoint_is_a_clear_error(runner, full_run_argv, tmp_path):
    out = tmp_path / "broken"
    described = runner.description_of(full_run_argv + ["--out", str(out)])
    rundir.open_run_dir(str(out), described, resume=False)
    step = out / "checkpoints" / "ppo_tl" / "1"
    step.mkdir(parents=True)
    (step / "junk").write_text("not a checkpoint")
    with pytest.raises(SystemExit) as info:
        runner.main(["--out", str(out), "--resume", "--methods", "ppo_tl", "comps"])
    assert info.value.code == 2


def test_report_regenerates_the_results(full_run, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(full_run, copy, ignore=shutil.ignore_patterns("checkpoints"))
    (copy / "results.json").unlink()
    shutil.rmtree(copy / "plots")
    report.write(str(copy))
    a = json.loads((full_run / "results.json").read_text())
    b = json.loads((copy / "results.json").read_text())
    assert a == b and (copy / "plots" / "iterations_to_success.png").exists()
    # Any method of the run can be the reference of the significance table.
    other = report.write(str(copy), baseline="ppo_tl")["significance"]
    assert other["baseline"] == "ppo_tl" and list(other["against"]) == ["comps"]
    assert other["against"]["comps"]["mean_a"] == a["significance"]["against"]["ppo_tl"]["mean_b"]
    assert "| ppo_tl vs |" in (copy / "significance.md").read_text()
    with pytest.raises(RunError, match="--baseline gmps: not a method of this run; its methods: comps"):
        report.write(str(copy), baseline="gmps")


def test_a_stopped_run_reports_the_tasks_every_method_has_finished(runner, merge_runs, full_run, full_run_argv,
                                                                   tmp_path):
    out = tmp_path / "stopped"
    described = runner.description_of(full_run_argv + ["--out", str(out)])
    rundir.open_run_dir(str(out), described, resume=False)
    for name, chunks in (("comps", 2), ("ppo_tl", 1)):  # stopped after 2 and 1 of the 3 tasks
        experiment.run_method(str(out), name, described, resume=False,
                              programs=runner.PROGRAMS, stop_after_chunks=chunks)
    with pytest.raises(RunError, match="comps has not finished; .* with --partial"):
        report.write(str(out))
    got = report.write(str(out), partial=True)
    assert got["partial"] == {"tasks": 1, "of": 3, "tasks_done": {"comps": 2, "ppo_tl": 1}}
    full = json.loads((full_run / "results.json").read_text())
    for name in ("comps", "ppo_tl"):
        mine, theirs = got["methods"][name], full["methods"][name]
        assert mine["iterations_to_success"] == [row[:1] for row in theirs["iterations_to_success"]]
        assert mine["heldout"]["after_tasks"] == [0, 1]
        assert mine["heldout"]["adapted_return"] == [row[:2] for row in theirs["heldout"]["adapted_return"]]
    assert (out / "significance.md").read_text().startswith("Unfinished run: tasks 1-1 of 3")
    # Merged with --partial, the same report; without it, the merge says what to do.
    with pytest.raises(RunError, match="comps has not finished; .* --partial"):
        merge_runs.merge(str(tmp_path / "m"), [str(out)])
    merged = merge_runs.merge(str(tmp_path / "m2"), [str(out)], partial=True)
    assert merged["methods"] == got["methods"] and merged["partial"] == got["partial"]
    # A method that has not finished a chunk leaves nothing to report.
    os.remove(results.partial_path(str(out), "ppo_tl"))
    with pytest.raises(RunError, match="ppo_tl has not finished a chunk of tasks yet"):
        report.write(str(out), partial=True)


@pytest.mark.parametrize("argv,message", [
    (["--methods", "maml"], "methods='maml'; allowed: ppo_tl, ppo, comps, gmps, gmps_ppo, gmps_ppo_is, gmps_ppo_last, "
                            "gmps_ppo_is_last, gmps_ppo_is_x2"),
    (["--family", "humanoid"], "family='humanoid'; allowed:"),
    (["--budget", "0"], "budget=0"),
    (["--budget", "-3"], "budget=-3"),
    (["--learning-rate", "abc"], "argument --learning-rate: expected a number, got 'abc'"),
    (["--learning-rate", "inf"], "argument --learning-rate: expected a finite number, got 'inf'"),
    (["--set", "comps.meta.outer_learning_rate=nan"], "--set comps.meta.outer_learning_rate: .*finite number"),
    (["--budget", "abc"], "argument --budget: expected an integer or none, got 'abc'"),
    (["--devices", "99"], "--devices 99: this machine has [0-9]+ cores; allowed: 1 to"),
    (["--compile-cache", "none", "--hidden-sizes", "64", "x"], "argument --hidden-sizes: expected an integer"),
    (["--seeds", "0"], "seeds=0"),
    (["--chunk-tasks", "0"], "chunk_tasks=0"),
    (["--num-tasks", "41"], re.escape("--num-tasks must be in [1, 40]")),
    (["--sequence", "shuffled"], "sequence='shuffled'"),
    (["--methods", "comps", "--num-tasks", "5", "--max-tasks", "3"], "--max-tasks 3 is smaller than --num-tasks 5"),
    (["--methods", "comps", "--inner-learning-rate", "-0.1"], "inner_learning_rate=-0.1"),
    (["--backward-tasks", "-1"], "backward_tasks=-1"),
    (["--learnt-eval", "never"], "learnt_eval='never'; allowed: chunk, end"),
    (["--devices", "0"], "--devices must be >= 1"),
    (["--resume"], "--resume needs --out"),
    (["--methods", "comps", "ppo_tl", "--baseline", "gmps"],
     r"--baseline gmps: not a method of this run; its methods: comps, ppo_tl"),
])
def test_bad_options_exit_2_with_a_message(runner, argv, message, capsys):
    extra = [] if "--resume" in argv else ["--out", "/nonexistent/x"]
    with pytest.raises(SystemExit) as info:
        runner.description_of(argv + extra)
    assert info.value.code == 2
    assert re.search(message, capsys.readouterr().err)


def test_resume_of_a_finished_run_rewrites_nothing_it_has(runner, full_run, capsys):
    before = _raw(full_run, "comps")
    runner.main(["--out", str(full_run), "--resume"])
    assert "already finished" in capsys.readouterr().out
    after = _raw(full_run, "comps")
    for key in before:
        np.testing.assert_array_equal(before[key], after[key])


def test_runs_made_before_the_learnt_tasks_evaluations_still_report(full_run, tmp_path):
    old = tmp_path / "old_raw"
    shutil.copytree(full_run, old, ignore=shutil.ignore_patterns("checkpoints", "plots", "results.json"))
    for path in (old / "raw").glob("*.npz"):
        with np.load(path) as f:
            kept = {k: f[k] for k in f.files if not k.startswith(("learnt", "backward_success"))}
            assert len(kept) < len(f.files)
        with open(path, "wb") as f:
            np.savez(f, **kept)
    raw = results.load(str(old), "comps")
    assert raw.per_task.learnt is None and raw.measured.learnt is None and raw.per_task.backward_success is None
    assert results.truncate(raw, 2).per_task.learnt is None
    got = report.write(str(old))
    full = json.loads((full_run / "results.json").read_text())
    for name in ("comps", "ppo_tl"):
        m = got["methods"][name]
        for key in ("forgetting", "average_performance"):
            assert "before jcomps evaluated the learnt tasks" in m[key]["note"]
        assert m["iterations_to_success"] == full["methods"][name]["iterations_to_success"]
    assert "| comps | n/a | n/a | n/a | – |" in (old / "significance.md").read_text()


def test_forgetting_with_the_learnt_tasks_evaluated_at_the_end_only(full_run):
    """With --learnt-eval end only the last row of the learnt tasks' evaluations is valid: forgetting and average
    performance come from it alone, and a run stopped before its end has none to report yet."""
    raw = results.load(str(full_run), "ppo_tl")
    every = report.learnt_summary(raw)
    valid = raw.measured.learnt.valid.copy()
    valid[:, :-1] = False
    end = report.learnt_summary(raw._replace(measured=raw.measured._replace(
        learnt=raw.measured.learnt._replace(valid=valid))))
    assert end["forgetting"]["by_evaluation"]["after_tasks"] == [3]
    assert end["forgetting"]["per_task"] == every["forgetting"]["per_task"]
    assert end["average_performance"]["mean"] == every["average_performance"]["mean"]
    none = report.learnt_summary(raw._replace(measured=raw.measured._replace(
        learnt=raw.measured.learnt._replace(valid=valid & False))))
    assert "--learnt-eval end" in none["forgetting"]["note"] and "note" in none["average_performance"]


def test_forward_transfer_against_a_merged_ppo_run(merge_runs, full_run, tmp_path):
    """A run of ppo merged beside a method's run is the reference of its forward transfer; here "ppo" is ppo_tl's
    results with every success rate set to 0.5 (AUC_ref = 0.5), so ppo_tl's FT = (0 − 0.5)/(1 − 0.5) = −1 where
    its own success stayed 0, and the reference's own FT is 0."""
    b = _one_method_copy(full_run, tmp_path / "b", "ppo_tl")
    c = _one_method_copy(full_run, tmp_path / "c", "ppo_tl")
    desc = json.loads((c / "run.json").read_text())
    desc["run"]["methods"], desc["methods"] = ["ppo"], {"ppo": desc["methods"]["ppo_tl"]}
    (c / "run.json").write_text(json.dumps(desc))
    with np.load(c / "raw" / "ppo_tl.npz") as f:
        arrays = {k: f[k] for k in f.files}
    (c / "raw" / "ppo_tl.npz").unlink()
    arrays["task.per_iteration.success_rate"] = np.full_like(arrays["task.per_iteration.success_rate"], 0.5)
    with open(c / "raw" / "ppo.npz", "wb") as f:
        np.savez(f, **arrays)
    merged = merge_runs.merge(str(tmp_path / "m"), [str(b), str(c)], baseline="ppo")
    own = np.asarray(merged["methods"]["ppo_tl"]["success_rate_curves"], dtype=object)
    assert all(v == 0.0 for row in own for curve in row for v in curve)  # the tiny run never succeeds
    ft = merged["methods"]["ppo_tl"]["forward_transfer"]
    assert ft["reference"] == "ppo" and ft["horizon"] == 3 and ft["reference_auc"] == [[0.5] * 3] * 2
    assert ft["per_task"] == [[-1.0] * 3] * 2 and ft["mean"] == -1.0
    assert merged["methods"]["ppo"]["forward_transfer"]["per_task"] == [[0.0] * 3] * 2
    # The same iterations-to-success as the baseline: probability of improvement 1/2.
    assert merged["significance"]["probability_of_improvement"]["ppo_tl"]["probability"] == 0.5
    assert (tmp_path / "m" / "plots" / "continual_metrics.png").exists()


def test_eval_config_rejects_bad_values():
    with pytest.raises(ValueError, match="heldout_iterations"):
        continual.EvalConfig(heldout_iterations=-1)
    with pytest.raises(ValueError, match="heldout_budget"):
        continual.EvalConfig(heldout_budget=-1)
    with pytest.raises(ValueError, match="learnt_eval='never'; allowed: chunk, end"):
        continual.EvalConfig(learnt_eval="never")
    with pytest.raises(ValueError, match="learnt_episodes=-2"):
        continual.EvalConfig(learnt_episodes=-2)


def test_two_host_devices_run_with_padded_seeds(tiny_options, tmp_path):
    """The script itself on 2 host devices (a fresh process: the device count is set before JAX starts), with 3
    seeds: they are padded to 4, two per device, and the results hold the 3 asked for."""
    import subprocess
    import sys

    script = os.path.join(os.path.dirname(__file__), "..", "experiments", "run_sequence.py")
    out = tmp_path / "two"
    args = tiny_options + ["--methods", "ppo_tl", "--num-tasks", "2", "--seeds", "3", "--chunk-tasks", "1",
                   "--devices", "2", "--out", str(out)]
    proc = subprocess.run([sys.executable, script] + args, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "3 seeds (+1 to fill the devices, not reported) on 2 device(s)" in proc.stdout
    m = json.loads((out / "results.json").read_text())["methods"]["ppo_tl"]
    assert m["devices"] == 2 and np.asarray(m["iterations_to_success"]).shape == (3, 2)
    assert np.asarray(m["heldout"]["adapted_return"]).shape == (3, 3)
    # Resuming it on another device count is refused: float rounding depends on it.
    proc = subprocess.run([sys.executable, script, "--out", str(out), "--resume", "--devices", "1"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 2
    assert "devices: run has 2, asked 1 (float rounding depends on it: resume with --devices 2)" in proc.stderr


def test_checkpoint_round_trip_with_empty_metrics(tmp_path):
    # --backward-tasks 0 makes the backward-transfer metrics zero-size arrays, which Orbax refuses to save: the
    # checkpoint leaves them out and the restore rebuilds them from the run's own shapes.
    states = {"w": np.arange(6, dtype=np.float32).reshape(2, 3)}
    per_task = {"returns": np.ones((2, 4), np.float32), "backward": np.zeros((2, 4, 0), np.float32)}
    heldout = (np.full((2, 1, 3), 0.5, np.float32),)
    checkpoints = checkpoint.Checkpoints(str(tmp_path / "ckpt"))
    checkpoints.save(1, checkpoint.record(states, per_task, heldout, 1, 2.5))
    like = checkpoint.record(jax.tree.map(np.zeros_like, states), jax.tree.map(np.zeros_like, per_task),
                              jax.tree.map(np.zeros_like, heldout), 0, 0.0)
    step, tree = checkpoints.restore_latest(like, print)
    assert step == 1 and int(tree["counters"]["next_chunk"]) == 1
    restored = checkpoint.unflatten(per_task, tree["per_task"])
    np.testing.assert_array_equal(restored["returns"], per_task["returns"])
    assert restored["backward"].shape == (2, 4, 0)
    np.testing.assert_array_equal(checkpoint.unflatten(states, tree["states"])["w"], states["w"])


def _one_method_copy(full_run, dest, name):
    """A copy of ``full_run`` as if it had run ``name`` alone."""
    shutil.copytree(full_run, dest, ignore=shutil.ignore_patterns("checkpoints", "plots", "results.json"))
    desc = json.loads((dest / "run.json").read_text())
    other = [m for m in desc["run"]["methods"] if m != name]
    desc["run"]["methods"] = [name]
    desc["methods"] = {name: desc["methods"][name]}
    (dest / "run.json").write_text(json.dumps(desc))
    for m in other:
        (dest / "raw" / f"{m}.npz").unlink()
    return dest


def test_merged_runs_report_as_one_run(merge_runs, full_run, tmp_path):
    a = _one_method_copy(full_run, tmp_path / "a", "comps")
    b = _one_method_copy(full_run, tmp_path / "b", "ppo_tl")
    merged = merge_runs.merge(str(tmp_path / "m"), [str(a), str(b)])
    assert merged == json.loads((full_run / "results.json").read_text()) | {"plots": merged["plots"]}
    assert (tmp_path / "m" / "plots" / "iterations_to_success.png").exists()
    with pytest.raises(RunError, match="already holds a run"):
        merge_runs.merge(str(tmp_path / "m"), [str(a), str(b)])
    with pytest.raises(RunError, match="comps is in more than one source"):
        merge_runs.merge(str(tmp_path / "m2"), [str(a), str(a)])
    # A method run with other chunking (checkpoints after every task) merges; its results are its own.
    desc = json.loads((b / "run.json").read_text())
    desc["run"]["chunk_tasks"] += 1
    (b / "run.json").write_text(json.dumps(desc))
    assert merge_runs.merge(str(tmp_path / "m1"), [str(a), str(b)])["methods"] == merged["methods"]
    chunks = json.loads((tmp_path / "m1" / "run.json").read_text())["run"]["chunk_tasks_by_method"]
    assert chunks == {"comps": desc["run"]["chunk_tasks"] - 1, "ppo_tl": desc["run"]["chunk_tasks"]}
    desc["run"]["seeds"] = 3
    (b / "run.json").write_text(json.dumps(desc))
    with pytest.raises(RunError, match=r"not the same study as .*run.seeds: run has 2, asked 3"):
        merge_runs.merge(str(tmp_path / "m3"), [str(a), str(b)])
    (a / "raw" / "comps.npz").unlink()
    with pytest.raises(RunError, match="comps has not finished"):
        merge_runs.merge(str(tmp_path / "m4"), [str(a)])
    # The finished methods of a run whose others are still going.
    shutil.rmtree(tmp_path / "m")
    only = merge_runs.merge(str(tmp_path / "m"), [str(full_run)], methods_=["ppo_tl"])
    assert list(only["methods"]) == ["ppo_tl"] and only["methods"]["ppo_tl"] == merged["methods"]["ppo_tl"]
    with pytest.raises(RunError, match="--methods gmps: not in the sources; they have comps, ppo_tl"):
        merge_runs.merge(str(tmp_path / "m5"), [str(full_run)], methods_=["gmps"])


def test_render_draws_point_goal_episodes(render, full_run, tmp_path):
    lines = []
    paths = render.render(str(full_run), tasks=[1, 3], out_dir=str(tmp_path), print_fn=lines.append)
    assert [p.split("/")[-1] for p in paths] == ["comps_seed0_task01.png", "comps_seed0_task03.png",
                                                 "ppo_tl_seed0_task01.png", "ppo_tl_seed0_task03.png"]
    assert all(os.path.getsize(p) > 1000 for p in paths)
    assert all(re.search(r"success rate \d\.\d\d over 2 episodes \(threshold 0\.7\)", line) for line in lines)


def test_read_latest_skips_an_unreadable_step_and_changes_nothing(full_run, tmp_path):
    copy = tmp_path / "ckpt"
    shutil.copytree(full_run / "checkpoints" / "ppo_tl", copy)
    steps = sorted(int(p.name) for p in copy.iterdir() if p.name.isdigit())
    step, tree = checkpoint.read_latest(str(copy), print)
    assert step == steps[-1] and int(tree["counters"]["next_chunk"]) == steps[-1]
    for path in (copy / str(steps[-1])).rglob("*"):
        if path.is_file():
            path.write_bytes(b"garbage")
    before = sorted(str(p) for p in tmp_path.rglob("*"))
    warnings = []
    step, tree = checkpoint.read_latest(str(copy), warnings.append)
    assert step == steps[-2] and "cannot be read" in warnings[0]
    assert sorted(str(p) for p in tmp_path.rglob("*")) == before  # read-only: nothing moved or written
    assert checkpoint.read_latest(str(tmp_path / "none"), print) is None


def test_to_host_takes_empty_arrays_sharded_over_devices():
    """No backward-transfer tasks make [members, tasks, 0] metrics sharded over the members' devices; jax's
    device_get cannot assemble such an empty array (it crashed every multi-device run with --backward-tasks 0)."""
    devices = jax.devices()
    if len(devices) < 2:
        pytest.skip("needs two host devices")
    sharding = jax.sharding.NamedSharding(jax.sharding.Mesh(np.array(devices[:2]), ("m",)),
                                          jax.sharding.PartitionSpec("m"))
    # As the programs make it: an empty output of a compiled program, sharded over the devices.
    empty = jax.jit(lambda x: x * 2, out_shardings=sharding)(jax.device_put(np.zeros((2, 3, 0), np.float32), sharding))
    with pytest.raises(ValueError, match="could not broadcast"):  # jax 0.10's own device_get (if fixed: drop to_host)
        jax.device_get(empty)
    full = jax.device_put(np.arange(6, dtype=np.float32).reshape(2, 3), sharding)
    out = experiment.to_host({"empty": empty, "full": full})
    assert out["empty"].shape == (2, 3, 0) and out["empty"].dtype == np.float32
    np.testing.assert_array_equal(out["full"], np.arange(6).reshape(2, 3))


def test_chosen_tasks_are_learnt_recorded_and_checked_on_resume(runner, full_run, full_run_argv, tmp_path, capsys):
    """``--tasks`` replaces the family's list: the family's own first three tasks named explicitly give the very
    run of ``full_run``, array for array; run.json records them, the start line names them, and a resume with
    other tasks is refused."""
    from jcomps import envs

    chosen = [f"{v:g}" for v in envs.sequence_values("point_goal", "non-stationary", 0, 3)]
    out = tmp_path / "chosen"
    runner.main(full_run_argv + ["--tasks", *chosen, "--out", str(out)])
    assert f"point_goal tasks {' '.join(chosen)}, 2 seeds" in capsys.readouterr().out
    stored = json.loads((out / "run.json").read_text())
    assert stored["run"]["tasks"] == chosen
    for name in ("comps", "ppo_tl"):
        a, b = _raw(full_run, name), _raw(out, name)
        assert a.keys() == b.keys()
        for key in a:
            np.testing.assert_array_equal(a[key], b[key], err_msg=f"{name} {key}")
    with pytest.raises(SystemExit) as info:
        runner.main(["--out", str(out), "--resume", "--tasks", *chosen[::-1]])
    assert info.value.code == 2 and "tasks" in capsys.readouterr().err
    runner.main(["--out", str(out), "--resume"])
    assert "already finished" in capsys.readouterr().out
    runner.main(["--out", str(out), "--resume", "--tasks", *[f"{float(t):.2f}" for t in chosen]])  # written otherwise
    assert "already finished" in capsys.readouterr().out
    # The same tasks in another order are another run: the chosen list, not the family's, reaches the programs.
    other = tmp_path / "reordered"
    runner.main(full_run_argv + ["--methods", "ppo_tl", "--tasks", *chosen[::-1], "--out", str(other)])
    a, b = _raw(full_run, "ppo_tl"), _raw(other, "ppo_tl")
    assert any(not np.array_equal(a[key], b[key]) for key in a)


def test_a_full_disk_stops_a_checkpoint_with_a_clear_error_and_keeps_the_ones_before(tmp_path, monkeypatch):
    """Too little space for the next step (measured from the newest step on disk): RunError naming the step, the
    directory and --resume, before Orbax writes anything; the steps before stay readable. (Tried on a 600 KB tmpfs:
    exit code 2, no traceback, and --resume finished the run once the disk had space.)"""
    import collections
    import errno

    states = {"w": np.arange(6, dtype=np.float32).reshape(2, 3)}
    tree = checkpoint.record(states, {"r": np.ones((2, 4), np.float32)}, (np.zeros((2, 1, 3), np.float32),), 1, 1.0)
    checkpoints = checkpoint.Checkpoints(str(tmp_path / "ckpt"))
    checkpoints.save(1, tree)
    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10**6, 10**6 - 1000, 1000))
    with pytest.raises(RunError, match=r"no space left on the device for checkpoint step 2 in .*ckpt .*"
                                                  r"--resume \(from its last checkpoint, step 1\)"):
        checkpoints.save(2, tree)
    assert checkpoints.manager.all_steps() == [1] and sorted(os.listdir(tmp_path / "ckpt")) == ["1"]
    # A disk that fills while Orbax writes (the estimate was short: tried on a 200 KB tmpfs, Orbax's writer fails
    # with RESOURCE_EXHAUSTED and prints nothing): the same RunError, its temporary step removed, step 1 kept.
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10**9, 0, 10**9))

    def fills(step, args, force):
        os.makedirs(tmp_path / "ckpt" / f"{step}.orbax-checkpoint-tmp-1")
        raise ValueError('RESOURCE_EXHAUSTED: Error writing "counters.seconds/0" in OCDBT database')

    monkeypatch.setattr(checkpoints.manager, "save", fills)
    with pytest.raises(RunError, match=r"no space left on the device writing checkpoint step 2 .*"
                                                  r"--resume \(from its last checkpoint, step 1\)"):
        checkpoints.save(2, tree)
    assert sorted(os.listdir(tmp_path / "ckpt")) == ["1"]
    assert checkpoints.restore_latest(tree, print)[0] == 1
    assert checkpoint.disk_full(OSError(errno.ENOSPC, "No space left on device"))
    assert checkpoint.disk_full(ValueError("RESOURCE_EXHAUSTED: Error writing local file"))
    assert not checkpoint.disk_full(ValueError("checkpoint entries differ"))


def test_the_library_path_and_the_runner_learn_the_same_sequence(full_run):
    """``continual.run_seeds`` (a whole sequence as one ``lax.scan`` over tasks, vmapped over seeds: the path for
    library users) and the runner (a host loop over tasks of one compiled ``learn`` program per position, members
    sharded over devices) learn the same tasks from the same keys: their per-task metrics agree. Not bit for bit:
    the two are compiled as different programs (a scan over tasks against one program per position, and the
    runner's members split over 2 devices), so XLA rounds some floats differently (on this tiny run one return of
    18 by 1.5e-5); the iterations, what was solved and which iterations ran are equal, the returns and success
    rates to 1e-5. Over hundreds of iterations such differences can change a run (docs/results.md, Ant Direction's
    task 1 across programs), so the runner is the path the studies use."""
    from jcomps import envs, methods
    from jcomps.runner import members

    stored = rundir.read(str(full_run))
    family = envs.make(stored.run.family)
    tasks = envs.sequence(family, stored.run.sequence, num_tasks=stored.run.num_tasks)
    for name in stored.run.methods:
        method = methods.make(name, family, stored.methods[name])
        _, metrics = continual.run_seeds(method, tasks, members.method_keys(stored.run.seed_list))
        raw = results.load(str(full_run), name)
        np.testing.assert_array_equal(np.asarray(metrics.iterations), raw.per_task.task.iterations, err_msg=name)
        np.testing.assert_array_equal(np.asarray(metrics.solved), raw.per_task.task.solved, err_msg=name)
        valid = raw.per_task.task.per_iteration.valid.astype(bool)
        np.testing.assert_array_equal(np.asarray(metrics.per_iteration.valid).astype(bool), valid, err_msg=name)
        for field in ("mean_return", "success_rate"):
            ours = np.asarray(getattr(metrics.per_iteration, field))[valid]
            np.testing.assert_allclose(ours, getattr(raw.per_task.task.per_iteration, field)[valid], rtol=1e-5,
                                       atol=1e-5, err_msg=f"{name} {field}")
