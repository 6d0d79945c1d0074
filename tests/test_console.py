"""Tests of the runner's console (``jcomps.console``): the runner's events turned into progress lines,
TensorBoard logs and (offline) Weights & Biases runs."""

import numpy as np

from jcomps import continual
from jcomps.methods.base import TaskMetrics
from jcomps.runner import events
from jcomps.training.ppo import IterationMetrics


def _chunk_metrics(seeds, tasks, budget, nonfinite_at=None):
    z = np.zeros((seeds, tasks, budget), np.float32)
    valid = np.ones((seeds, tasks, budget), bool)
    nonfinite = z.copy()
    if nonfinite_at is not None:
        nonfinite[nonfinite_at] = 1.0
    task = TaskMetrics(np.full((seeds, tasks), budget, np.int32), np.zeros((seeds, tasks), bool),
                       IterationMetrics(z - 5.0, z, z, z + 0.25, z, z, z + 0.5, nonfinite, valid))
    return continual.ChunkMetrics(task, np.zeros((seeds, tasks, 0), np.float32), np.zeros((seeds, tasks, 0), bool))


def _start_event(seeds=2, padding=0, **changes):
    """The runner's ``start`` event of a CoMPS program (members: the seeds and the padding), with ``changes``."""
    fields = dict(program="comps", family="cheetah_vel", sequence="non-stationary", num_tasks=2, tasks=(),
                  seeds=seeds, grid_points=1, padding=padding, devices=2, budget=4, chunk=2, start_task=0,
                  members=tuple(f"comps seed {s}" for s in range(seeds + padding)))
    return events.Start(**{**fields, **changes})


def test_console_turns_runner_events_into_lines(console, tmp_path):
    lines = []
    show = console.Console(lines.append, str(tmp_path), interval=0.0)
    show(_start_event(family="point_goal", sequence="stationary", seeds=3, padding=1, chunk=1))
    show(events.Iteration(program="comps", member=1, task=0, iteration=3, success_rate=0.5, mean_return=-3.0,
                          value_ev=0.8))
    show(events.MetaStep(program="comps", member=1, task=0, meta_step=7, meta_steps=125, bc_loss=1.25))
    show(events.CompressIteration(program="comps", member=0, task=0, compress_iteration=2, compress_iterations=15,
                                  kl=0.5))
    metrics = _chunk_metrics(3, 1, 4, nonfinite_at=(2, 0, 1))
    show(events.Chunk(program="comps", entry="comps", start=0, stop=1, num_tasks=2, seeds=(0, 1, 2), metrics=metrics,
                      per_task=metrics))
    show(events.Warned(message="checkpoint step 2 cannot be read"))
    show(events.Done(program="comps", seconds=75.0))
    assert lines[0] == ("[comps] point_goal stationary, 2 tasks, 3 seeds (+1 to fill the devices, not reported) on 2 "
                        "device(s), budget 4, chunks of 1")
    assert lines[1].startswith("[comps] task 1/2 iteration 3 success 0.12 critic EV 0.80")
    assert lines[2].startswith("[comps] task 1/2 meta-training step 7/125 bc loss 1.250")
    assert lines[3].startswith("[comps] task 1/2 compress iteration 2/15 kl ")  # pnc's compress phase
    assert lines[4] == ("[comps] task 1/2 iterations-to-success per seed: [4, 4, 4] (mean 4.0); critic EV 0.50 "
                        "(last update 0.50), value loss 0.25")
    assert lines[5].startswith("error: [comps] non-finite values (NaN/inf) at seed 2, task 1, iteration 2")
    assert lines[6] == "warning: checkpoint step 2 cannot be read" and lines[7] == "[comps] done in 1m15s"


def test_console_says_what_compiles_and_evaluates(console, tmp_path):
    """No silent phase: every compile says what and how long, the held-out meta-test shows its progress."""
    lines = []
    show = console.Console(lines.append, str(tmp_path), interval=0.0)
    show(_start_event())
    where = {"program": "comps", "family": "cheetah_vel", "method": "comps"}
    show(events.Compiling(part="learn", what="learning", **where))
    show(events.StillCompiling(part="learn", what="learning", seconds=20.5, **where))
    show(events.Compiled(part="learn", what="learning", seconds=95.0, trace_seconds=12.0, **where))
    show(events.Compiling(part="measure", what="held-out", **where))
    show(events.Compiled(part="measure", what="held-out", seconds=13.5, trace_seconds=12.0, cached=True, **where))
    show(events.Evaluating(program="comps", after_tasks=0, learnt=0))
    show(events.HeldoutIteration(program="comps", member=1, heldout_task=7, heldout_iteration=3, success_rate=0.0,
                                 mean_return=-1.0))
    show(events.Evaluated(program="comps", after_tasks=0, seconds=42.0))
    show(events.Evaluating(program="comps", after_tasks=2, learnt=2, adapts=False))
    assert lines[1] == "[comps] compiling the learning program (cheetah_vel, comps)..."
    assert lines[2] == "[comps] still compiling the learning program: 0m20s"
    assert lines[3] == "[comps] learning program ready in 1m35s (tracing 12s)"
    assert lines[4].endswith("(while the first task trains)...")
    assert lines[5] == "[comps] held-out program ready in 0m13s (tracing 12s; from the compile cache)"
    assert lines[6] == "[comps] held-out meta-test of the initial policies..."
    assert lines[7].startswith("[comps] held-out meta-test: 8 held-out tasks, iteration 3 (slowest 0) | elapsed")
    assert lines[8] == "[comps] evaluations after 0 task(s) done in 0m42s"
    assert lines[9] == "[comps] held-out zero-shot return and learnt tasks of the policies after task 2..."


def test_console_shows_the_meta_steps_health(console, tmp_path):
    from jcomps.training import meta

    lines = []
    show = console.Console(lines.append, str(tmp_path), interval=0.0)
    show(_start_event(num_tasks=3, devices=1, chunk=1, start_task=1))
    show(events.MetaStep(program="comps", member=0, task=1, meta_step=3, meta_steps=125, bc_loss=-3.0, value_l2=0.25,
                         value_ev=0.8, adv_abs=0.4, rho=0.5, inner_gain=0.125))
    assert lines[-1].startswith("[comps] task 2/3 meta-training step 3/125 bc loss -3.000 value l2 0.25 EV 0.80 "
                                "|A| 0.4 rho 0.50 inner gain +0.125")
    # After task 2 (slot 1): slots 0 and 1 seen, slot 2 not (NaN); two seeds.
    per_slot = lambda a, b: np.array([[[a, b, np.nan]], [[a, b, np.nan]]], np.float32)  # noqa: E731 - [S, 1, 3]
    fields = len(meta.SlotStats._fields)
    start = meta.SlotStats(*[per_slot(0.5, 0.5)] * fields)._replace(value_ev=per_slot(0.6, 0.2))
    end = start._replace(value_ev=per_slot(0.7, 0.9), rho=per_slot(0.4, 0.8), value_bias=per_slot(0.1, 0.3),
                         return_std=per_slot(1.0, 1.0), inner_gain=per_slot(0.25, -0.05))
    steps = meta.SlotStats(*[np.zeros((2, 1, 5), np.float32)] * fields)
    chunk = _chunk_metrics(2, 1, 4)
    chunk = chunk._replace(task=chunk.task._replace(meta=meta.MetaMetrics(steps, start, end)))
    show(events.Chunk(program="comps", entry="comps", start=1, stop=2, num_tasks=3, seeds=(0, 1), metrics=chunk,
                      per_task=chunk))
    assert lines[-1] == ("[comps] task 2/3 meta phase: heads' EV on returns 0.40 -> 0.80 (newest head 0.20 -> 0.90), "
                         "bias/std +0.20, mean rho 0.60 (oldest task 0.40), |A| 0.5, bc loss 0.500, inner gain +0.1 "
                         "(newest task -0.05)")


def test_console_shows_the_learnt_tasks_success_and_forgetting(console, tmp_path):
    lines = []
    show = console.Console(lines.append, str(tmp_path), interval=0.0)
    metrics = _chunk_metrics(2, 2, 3)
    # Right after learning: seed 0 0.8 and 0.6, seed 1 1.0 and 0.6; after task 2: 0.4, 0.6 and 0.8, 0.6.
    when = continual.Evaluation(np.zeros((2, 2), np.float32), np.array([[0.8, 0.6], [1.0, 0.6]], np.float32),
                                np.ones((2, 2), bool))
    per_task = metrics._replace(learnt=when)
    now = continual.Evaluation(np.zeros((2, 2), np.float32), np.array([[0.4, 0.6], [0.8, 0.6]], np.float32),
                               np.ones((2, 2), bool))
    show(events.Chunk(program="comps", entry="comps", start=1, stop=2, num_tasks=4, seeds=(0, 1), metrics=per_task,
                      per_task=per_task, learnt_tasks=now))
    assert lines[-1] == ("[comps] after task 2/4: success on the 2 tasks learnt 0.60, right after learning each 0.75 "
                         "(forgetting +0.15)")
    # With --learnt-eval end nothing was evaluated after this chunk: no line.
    show(events.Chunk(program="comps", entry="comps", start=1, stop=2, num_tasks=4, seeds=(0, 1), metrics=per_task,
                      per_task=per_task, learnt_tasks=now._replace(valid=np.zeros((2, 2), bool))))
    assert not lines[-1].startswith("[comps] after task")


def _varied_chunk(seeds=2, tasks=2, budget=3):
    """Chunk metrics whose iterations, returns and critic differ by seed, task and iteration (the second seed's
    second task ran 2 iterations, the critic measured on the first iteration of each task only)."""
    metrics = _chunk_metrics(seeds, tasks, budget)
    it = metrics.task.per_iteration
    shape = (seeds, tasks, budget)
    ret = np.arange(np.prod(shape), dtype=np.float32).reshape(shape)
    valid = np.ones(shape, bool)
    valid[1, 1, 2] = False
    ev = np.full(shape, np.nan, np.float32)
    ev[:, :, 0] = 0.5
    iterations = valid.sum(-1).astype(np.int32)
    task = metrics.task._replace(iterations=iterations,
                                 per_iteration=it._replace(mean_return=ret, valid=valid, value_ev=ev))
    return metrics._replace(task=task)


def test_console_writes_the_scalars_to_tensorboard(console, tmp_path):
    import tensorboard_file

    show = console.Console(lambda line: None, str(tmp_path), tensorboard=True)
    metrics = _varied_chunk()
    show(events.Chunk(program="ppo_tl", entry="ppo_tl", start=0, stop=2, num_tasks=2, seeds=(0, 1), metrics=metrics,
                      per_task=metrics))
    show.close()
    [path] = (tmp_path / "tensorboard" / "ppo_tl").glob("events.out.tfevents*")
    logged = tensorboard_file.scalars(path)
    expected = {(tag, step): value for tag, value, _, step in console.chunk_scalars(metrics, 0, 2)}
    assert logged.keys() == expected.keys()
    np.testing.assert_allclose([logged[k] for k in expected], list(expected.values()), rtol=1e-6)


def test_the_scalars_are_the_metrics_on_their_axes(console):
    metrics = _varied_chunk()
    got = {(tag, axis, step): value for tag, value, axis, step in console.chunk_scalars(metrics, 0, 2)}
    assert got[("iterations_to_success/mean", "task", 2)] == 2.5
    assert got[("iterations_to_success/seed1", "task", 2)] == 2
    # The second seed's lifelong curve runs over its 5 iterations: 3 of task 1, then 2 of task 2.
    ret = metrics.task.per_iteration.mean_return
    assert [got[("lifelong_return/seed1", "iteration/seed1", n)] for n in range(1, 6)] == [
        ret[1, 0, 0], ret[1, 0, 1], ret[1, 0, 2], ret[1, 1, 0], ret[1, 1, 1]]
    assert ("lifelong_return/seed1", "iteration/seed1", 6) not in got
    # The critic where it was measured only (the first iteration of each task).
    assert sorted(k[2] for k in got if k[0] == "critic_ev/seed0") == [1, 4]


def test_console_logs_the_same_scalars_to_an_offline_wandb_run(console, tmp_path, monkeypatch):
    """``--wandb``: one offline run per entry, no network or API key; its file holds every scalar TensorBoard
    gets, each on its axis."""
    import wandb_file

    for var in ("WANDB_MODE", "WANDB_API_KEY", "WANDB_BASE_URL"):
        monkeypatch.delenv(var, raising=False)
    for var in ("WANDB_CACHE_DIR", "WANDB_CONFIG_DIR", "WANDB_DATA_DIR"):
        monkeypatch.setenv(var, str(tmp_path / "wandb-home"))
    show = console.Console(lambda line: None, str(tmp_path), wandb="jcomps-test", wandb_group="study")
    metrics = _varied_chunk()
    show(events.Chunk(program="ppo_tl", entry="ppo_tl", start=0, stop=2, num_tasks=2, seeds=(0, 1), metrics=metrics,
                      per_task=metrics))
    show.close()
    [path] = (tmp_path / "wandb").glob("offline-run-*/run-*.wandb")
    rows = wandb_file.history(path)
    assert rows, f"no history in {path}; its records: {wandb_file.record_types(path)}"
    logged = {}
    for row in rows:
        axis = next(k for k in row if k == "task" or k.startswith("iteration/"))  # one axis per row
        logged.update({(tag, axis, row[axis]): value for tag, value in row.items() if tag != axis})
    expected = {(tag, axis, step): value for tag, value, axis, step in console.chunk_scalars(metrics, 0, 2)}
    assert logged.keys() == expected.keys()
    np.testing.assert_allclose([logged[k] for k in expected], list(expected.values()), rtol=1e-6)
    axes = wandb_file.step_metrics(path)
    assert axes["iterations_to_success/*"] == "task" and axes["lifelong_return/seed1"] == "iteration/seed1"


def test_every_kind_of_event_is_shown_or_deliberately_left_out(console, tmp_path):
    show = console.Console(lambda line: None, str(tmp_path))
    assert len({cls.kind for cls in events.EVENTS}) == len(events.EVENTS)  # one kind per class: JSON round trips
    # The library path's task ends (continual.run_tasks) and a method's own phases have no line of their own.
    assert set(events.EVENTS) - set(show.handlers) - set(show.member_handlers) == {events.TaskEnd,
                                                                                  events.MemberProgress}
