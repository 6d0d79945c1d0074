"""Tests of the report of a run directory (``jcomps.analysis.report``): ``results.json``, the tables and the plots of a
tiny hand-made run (numpy arrays written as ``raw/<entry>.npz``; nothing is trained or compiled)."""

import json
import os

import numpy as np
import pytest

from jcomps.analysis import report, statistics
from jcomps.runner import grid, rundir
from jcomps.runner.files import RunError

S, N, BUDGET, H = 2, 2, 3, 2  # seeds, tasks, RL-step budget, held-out tasks
AFTER = np.array([0, 1, 2])  # tasks learnt before each held-out measurement
ITERATIONS = {"comps": np.array([[1, 2], [2, 3]]), "ppo_tl": np.array([[3, 3], [2, 2]])}


def _arrays(iterations: np.ndarray, seed: int) -> dict:
    """The raw results of one entry: ``iterations`` [S, N] and arrays drawn from ``seed`` for the rest."""
    rng = np.random.default_rng(seed)
    valid = np.arange(BUDGET) < iterations[..., None]
    curve = lambda: rng.uniform(0.0, 1.0, (S, N, BUDGET)).astype(np.float32)  # noqa: E731
    learnt_tasks_valid = np.broadcast_to(np.arange(N) < AFTER[:, None], (S, len(AFTER), N))
    return {
        "task.iterations": iterations.astype(np.int32),
        "task.solved": iterations < BUDGET,
        **{f"task.per_iteration.{k}": curve() for k in ("mean_return", "success_rate", "policy_loss", "value_loss",
                                                         "entropy", "approx_kl", "value_ev")},
        "task.per_iteration.nonfinite": np.zeros((S, N, BUDGET), np.float32),
        "task.per_iteration.valid": valid,
        "backward_returns": rng.uniform(0.0, 1.0, (S, N, 1)).astype(np.float32),
        "backward_valid": np.array([[[False], [True]]] * S),
        "heldout.mean_return": rng.uniform(0.0, 1.0, (S, len(AFTER), H, 2)).astype(np.float32),
        "heldout.success_rate": rng.uniform(0.0, 1.0, (S, len(AFTER), H, 2)).astype(np.float32),
        "heldout.iterations": rng.integers(1, 4, (S, len(AFTER), H)).astype(np.int32),
        "heldout.solved": np.ones((S, len(AFTER), H), bool),
        "heldout_after_tasks": AFTER,
        "seconds": np.float64(1.5),
        "devices": np.int64(1),
        "learnt.mean_return": rng.uniform(0.0, 1.0, (S, N)).astype(np.float32),
        "learnt.success_rate": rng.uniform(0.0, 1.0, (S, N)).astype(np.float32),
        "learnt.valid": np.ones((S, N), bool),
        "learnt_tasks.mean_return": rng.uniform(0.0, 1.0, (S, len(AFTER), N)).astype(np.float32),
        "learnt_tasks.success_rate": rng.uniform(0.0, 1.0, (S, len(AFTER), N)).astype(np.float32),
        "learnt_tasks.valid": learnt_tasks_valid.copy(),
    }


def _save(path, arrays: dict) -> None:
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "wb") as f:
        np.savez(f, **arrays)


@pytest.fixture
def run_dir(tmp_path):
    """A finished run of comps and ppo_tl on Point Goal: 2 seeds, 2 tasks; returns (directory, raw arrays)."""
    description = {
        "run": {"family": "point_goal", "sequence": "non-stationary", "methods": ["comps", "ppo_tl"], "seeds": S,
                "seed": 0, "num_tasks": N, "chunk_tasks": 1},
        "eval": {"backward_tasks": 1, "heldout_iterations": 1, "heldout_budget": 3, "learnt_eval": "chunk",
                 "learnt_episodes": 0},
        "methods": {"comps": {}, "ppo_tl": {}},
        "devices": 1,
    }
    (tmp_path / "run.json").write_text(json.dumps(description))
    raws = {name: _arrays(its, k) for k, (name, its) in enumerate(ITERATIONS.items())}
    for name, arrays in raws.items():
        _save(tmp_path / "raw" / f"{name}.npz", arrays)
    return tmp_path, raws


def test_results_json_of_a_hand_made_run(run_dir):
    out, raws = run_dir
    got = report.write(str(out))
    assert json.loads((out / "results.json").read_text()) == got
    assert got["seeds"] == [0, 1] and list(got["methods"]) == ["comps", "ppo_tl"]
    for name, its in ITERATIONS.items():
        m, raw = got["methods"][name], raws[name]
        assert m["iterations_to_success"] == its.tolist()
        np.testing.assert_allclose(m["iterations_to_success_mean"], its.mean(0), atol=1e-3)
        np.testing.assert_allclose(m["iterations_to_success_se"], its.std(0, ddof=1) / np.sqrt(S), atol=1e-3)
        # Point Goal: 20 episodes of 100 steps per PPO iteration.
        assert m["env_steps_per_iteration"] == 2000 and m["env_steps_to_success"] == (its * 2000).tolist()
        valid, ret = raw["task.per_iteration.valid"], raw["task.per_iteration.mean_return"]
        assert [[len(c) for c in row] for row in m["return_curves"]] == its.tolist()
        per_task = [[ret[s, t][valid[s, t]].mean() for t in range(N)] for s in range(S)]
        np.testing.assert_allclose(m["mean_return_per_task"], per_task, atol=1e-6)
        # Backward transfer after task 2 on task 1: (c − first)/(last − first); none after task 1, nor where task
        # 1 took one iteration (first = last).
        first, last = ret[:, 0, 0], ret[np.arange(S), 0, its[:, 0] - 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            expected = np.where(first == last, np.nan, (raw["backward_returns"][:, 1, 0] - first) / (last - first))
        assert [row[0] for row in m["backward_transfer"]] == [None, None]
        got_bt = np.array([np.nan if row[1] is None else row[1] for row in m["backward_transfer"]])
        np.testing.assert_allclose(got_bt, expected, rtol=1e-5)
        # Forgetting after the last task: success when learnt − success at the end.
        forgetting = raw["learnt.success_rate"] - raw["learnt_tasks.success_rate"][:, -1]
        np.testing.assert_allclose(m["forgetting"]["per_task"], forgetting, atol=1e-6)
        assert m["forgetting"]["by_evaluation"]["after_tasks"] == [1, 2]
        assert "no ppo" in m["forward_transfer"]["note"] and "meta" not in m
        assert m["heldout"]["after_tasks"] == AFTER.tolist() and m["heldout"]["budget"] == 3
        assert [q["tasks"] for q in m["iqm"]] == [[1, 1], [2, 2]]
        # The critic: over the iterations that updated (every valid one here: the curves are finite).
        ev, vl = raw["task.per_iteration.value_ev"], raw["task.per_iteration.value_loss"]
        np.testing.assert_allclose(m["critic"]["value_ev_mean"],
                                   [[ev[s, t][valid[s, t]].mean() for t in range(N)] for s in range(S)], atol=1e-6)
        np.testing.assert_allclose(m["critic"]["value_ev_last"], ev[np.arange(S)[:, None], np.arange(N), its - 1],
                                   atol=1e-6)
        np.testing.assert_allclose(m["critic"]["value_loss_mean"],
                                   [[vl[s, t][valid[s, t]].mean() for t in range(N)] for s in range(S)], atol=1e-6)
    sig = got["significance"]
    assert sig["baseline"] == "comps" and list(sig["against"]) == ["ppo_tl"]
    per_seed = {name: its.mean(1) for name, its in ITERATIONS.items()}
    assert sig["against"]["ppo_tl"] == statistics.significance(per_seed["comps"], per_seed["ppo_tl"])
    assert list(sig["probability_of_improvement"]) == ["ppo_tl"]
    # Every plot but the meta step's health (no method here reports one).
    assert got["plots"] == [f"plots/{p}.png" for p in (
        "iterations_to_success", "samples_to_success", "lifelong_return", "per_task_return", "backward_transfer",
        "heldout_meta_test", "critic", "performance_profile", "continual_metrics")]
    assert all((out / p).is_file() for p in got["plots"])
    table = (out / "significance.md").read_text()
    assert "| comps vs | comps mean | other mean |" in table and "| ppo_tl | 2.00 | 2.50 |" in table
    assert "| method | tasks 1-1 | tasks 2-2 |" in table and "P(fewer iterations than comps)" in table


def test_a_run_without_the_held_out_meta_test_reports_its_zero_shot_return_and_draws_no_held_out_plot(run_dir):
    """The default since issue 44 (``--heldout-iterations 0 --heldout-budget 0``): the held-out curve is the
    zero-shot return alone; results.json keeps it, and no held-out figure is drawn."""
    out, raws = run_dir
    description = json.loads((out / "run.json").read_text())
    description["eval"].update(heldout_iterations=0, heldout_budget=0)
    (out / "run.json").write_text(json.dumps(description))
    for name, arrays in raws.items():
        arrays = dict(arrays)
        for k in ("heldout.mean_return", "heldout.success_rate"):
            arrays[k] = arrays[k][..., :1]
        arrays["heldout.iterations"] = np.zeros_like(arrays["heldout.iterations"])
        arrays["heldout.solved"] = np.zeros_like(arrays["heldout.solved"])
        _save(out / "raw" / f"{name}.npz", arrays)
    got = report.write(str(out))
    for name, arrays in raws.items():
        h = got["methods"][name]["heldout"]
        assert h["adaptation_iterations"] == 0 and h["budget"] == 0
        np.testing.assert_allclose(h["zero_shot_return"], arrays["heldout.mean_return"][..., 0].mean(axis=2),
                                   atol=1e-6)
    assert "plots/heldout_meta_test.png" not in got["plots"] and "plots/critic.png" in got["plots"]
    assert not (out / "plots" / "heldout_meta_test.png").exists()


def test_a_run_made_before_the_inner_gain_was_measured_is_reported(run_dir):
    """A meta-learning run whose raw results predate the inner step's gain (issue 43): its other health fields
    are reported, the gain as unmeasured (null), and the meta step's health is drawn."""
    out, raws = run_dir
    rng = np.random.default_rng(7)
    fields = ("bc_loss", "value_l2", "value_ev", "value_ev_targets", "value_bias", "return_std", "adv_abs", "rho")
    seen = np.arange(N)[None, :, None] >= np.arange(N)[None, None, :]  # [1, task, slot]: slot seen after task
    arrays = dict(raws["comps"])
    for part, shape in (("steps", (S, N, 4)), ("start", (S, N, N)), ("end", (S, N, N))):
        for field in fields:
            x = rng.uniform(0.1, 1.0, shape).astype(np.float32)
            arrays[f"task.meta.{part}.{field}"] = x if part == "steps" else np.where(seen, x, np.nan)
    _save(out / "raw" / "comps.npz", arrays)
    got = report.write(str(out))
    health = got["methods"]["comps"]["meta"]
    assert np.asarray(health["rho_end"], dtype=float).shape == (S, N)
    assert health["inner_gain_end"] == [[None] * N] * S
    assert "plots/meta_health.png" in got["plots"] and (out / "plots" / "meta_health.png").is_file()


def test_a_run_made_before_the_critic_was_measured_is_reported(run_dir):
    """Raw results without the RL step's explained variance (issue 44): the critic's fields are null, and no
    critic plot is drawn; an iteration without an update (NaN) does not count."""
    out, raws = run_dir
    for name, arrays in raws.items():
        _save(out / "raw" / f"{name}.npz", {k: v for k, v in arrays.items() if k != "task.per_iteration.value_ev"})
    got = report.write(str(out))
    assert got["methods"]["comps"]["critic"]["value_ev_mean"] == [[None] * N] * S
    assert "plots/critic.png" not in got["plots"]
    arrays = dict(raws["ppo_tl"])
    ev = arrays["task.per_iteration.value_ev"].copy()
    ev[:, :, 1] = np.nan  # iteration 2 of every task made no update
    _save(out / "raw" / "ppo_tl.npz", {**arrays, "task.per_iteration.value_ev": ev})
    got = report.write(str(out))["methods"]["ppo_tl"]["critic"]
    its = ITERATIONS["ppo_tl"]  # seed 0 ran 3 iterations per task, seed 1 two
    np.testing.assert_allclose(got["value_ev_last"], np.where(its == 3, ev[:, :, 2], ev[:, :, 0]), atol=1e-6)
    np.testing.assert_allclose(got["value_ev_first"], ev[:, :, 0], atol=1e-6)


def test_the_baseline_is_any_method_of_the_run(run_dir):
    out, raws = run_dir
    description = rundir.read(str(out))
    loaded, cut = report.read_raws(str(out), description)
    assert cut is None and list(loaded) == ["comps", "ppo_tl"]
    other = report.summarize(description, loaded, baseline="ppo_tl")["significance"]
    assert other["baseline"] == "ppo_tl" and other["against"]["comps"]["mean_a"] == 2.5
    with pytest.raises(RunError, match="--baseline gmps: not a method of this run; its methods: comps, ppo_tl"):
        report.summarize(description, loaded, baseline="gmps")


def test_without_comps_there_is_no_significance_table_unless_a_baseline_is_named(run_dir):
    out, _ = run_dir
    description = rundir.read(str(out))
    description = description.only(["ppo_tl"])
    loaded, _ = report.read_raws(str(out), description)
    results = report.summarize(description, loaded)
    assert "significance" not in results
    table = report.significance_table(results)
    assert table.startswith("No significance table: the run has no `comps`")
    assert "| ppo_tl | " in table and "P(fewer" not in table
    assert report.grid_table(results, description.grid) == ""


def test_an_unfinished_run_reports_the_tasks_every_method_has_finished(run_dir):
    out, raws = run_dir
    os.remove(out / "raw" / "ppo_tl.npz")
    with pytest.raises(RunError, match="ppo_tl has not finished; .* with --partial"):
        report.write(str(out))
    with pytest.raises(RunError, match="ppo_tl has not finished a chunk of tasks yet"):
        report.write(str(out), partial=True)
    one_task = {k: (v[:, :1] if v.ndim >= 2 and k.startswith(("task.", "backward_", "learnt.")) else v)
                for k, v in raws["ppo_tl"].items()}
    keep = AFTER <= 1
    one_task.update({k: v[:, keep] for k, v in one_task.items() if k.startswith("heldout.")})
    one_task.update({k: v[:, keep, :1] for k, v in one_task.items() if k.startswith("learnt_tasks.")})
    one_task["heldout_after_tasks"] = AFTER[keep]
    _save(out / "raw" / "partial" / "ppo_tl.npz", one_task)
    description = rundir.read(str(out))
    loaded, cut = report.read_raws(str(out), description, partial=True)
    assert cut == {"tasks": 1, "of": 2, "tasks_done": {"comps": 2, "ppo_tl": 1}}
    assert all(raw.per_task.task.iterations.shape == (S, 1) for raw in loaded.values())
    results = report.summarize(description, loaded)
    assert results["methods"]["comps"]["iterations_to_success"] == ITERATIONS["comps"][:, :1].tolist()
    assert results["methods"]["comps"]["heldout"]["after_tasks"] == [0, 1]


def test_a_directory_without_a_run_is_named(tmp_path):
    with pytest.raises(RunError, match="holds no run"):
        report.write(str(tmp_path))


def test_the_grid_table_marks_each_methods_best_point():
    results = {"seeds": [0, 1],
               "best": {"ppo_tl": "ppo_tl[learning_rate=0.0003]"},
               "methods": {f"ppo_tl[learning_rate={v}]": {"method": "ppo_tl", "grid": {"learning_rate": v},
                                                          "overall": {"iterations_to_success_mean": its,
                                                                      "iterations_to_success_se": 0.5,
                                                                      "mean_return": None}}
                           for v, its in ((0.001, 3.0), (0.0003, 2.0))}}
    lines = report.grid_table(results, (grid.Axis("learning_rate", (0.001, 0.0003)),)).splitlines()
    assert lines[2] == "| method | learning_rate | iterations-to-success | mean return | |"
    assert lines[4] == "| ppo_tl | 0.001 | 3.00 ± 0.50 | n/a |  |"
    assert lines[5] == "| ppo_tl | 0.0003 | 2.00 ± 0.50 | n/a | **best** |"
