"""experiments/render.py on a tiny Half-Cheetah run: brax HTML viewers of the checkpointed policies."""

import base64
import json
import re
import zlib

import numpy as np
import pytest

from jcomps import envs
from jcomps.runner import experiment, programs, rundir

TINY = ["--family", "cheetah_vel", "--methods", "ppo_tl", "--num-tasks", "3", "--seeds", "2", "--chunk-tasks", "1",
        "--budget", "2", "--num-trajectories", "2", "--hidden-sizes", "8", "--num-updates", "1",
        "--minibatch-size", "16", "--backward-tasks", "0", "--heldout-iterations", "0"]


# A MuJoCo run compiles for minutes on a 2-core CPU: CI skips these (run them with `pytest -m slow`); the Point
# Goal replay test in test_experiment.py runs in CI.
pytestmark = pytest.mark.slow

PROGRAMS = programs.Programs()


@pytest.fixture(scope="module")
def stopped_run(runner, tmp_path_factory):
    """A tiny Half-Cheetah run stopped after 2 of its 3 tasks (as if killed): its checkpoints, no results."""
    out = tmp_path_factory.mktemp("render") / "stopped"
    described = runner.description_of(TINY + ["--out", str(out)])
    rundir.open_run_dir(str(out), described, False)
    experiment.run_method(str(out), "ppo_tl", described, False,
                          programs=PROGRAMS, stop_after_chunks=2)
    return out


def _frames(page: str) -> dict:
    """The episode brax's page carries (its system JSON, base64 of zlib)."""
    blob = re.search(r'var system = "([^"]+)"', page).group(1)
    return json.loads(zlib.decompress(base64.b64decode(blob)))


def test_render_writes_a_brax_viewer_of_the_last_task_learnt(render, stopped_run, tmp_path):
    lines = []
    paths = render.render(str(stopped_run), out_dir=str(tmp_path), print_fn=lines.append)
    assert [p.split("/")[-1] for p in paths] == ["ppo_tl_seed0_task02.html"]
    page = open(paths[0]).read()
    assert "Brax visualizer" in page and "cdn.jsdelivr.net/gh/google/brax" in page
    family = envs.make("cheetah_vel")
    value = envs.sequence_values(family, "non-stationary", 0, 3)[1]
    assert re.search(rf"ppo_tl, seed 0, task 2 \({value:g} m/s\): success rate [01]\.\d\d over 2 episodes "
                     r"\(threshold 0\.45\), mean return -?\d+\.\d", lines[0])
    frames = _frames(page)
    # One frame per state of the episode: the reset state and T_max steps; the torso moves.
    pos = np.asarray([x["pos"] for x in frames["states"]["x"]])
    assert pos.shape[0] == family.max_steps + 1 and pos.shape[2] == 3
    assert np.abs(pos[-1] - pos[0]).max() > 1e-3


def test_render_tasks_seeds_and_a_task_not_learnt_yet(render, stopped_run, tmp_path):
    lines = []
    paths = render.render(str(stopped_run), seed=1, tasks=[1, 3], mean=True, out_dir=str(tmp_path),
                          print_fn=lines.append)
    assert [p.split("/")[-1] for p in paths] == ["ppo_tl_seed1_task01.html", "ppo_tl_seed1_task03.html"]
    assert "over 2 episodes" in lines[0] and "not learnt" not in lines[0]
    assert "not learnt yet (the policy after task 2)" in lines[1]
    # A replay is reproducible; the mean action differs from a sampled one.
    again = render.render(str(stopped_run), seed=1, tasks=[1], mean=True, out_dir=str(tmp_path / "b"),
                          print_fn=lambda line: None)
    assert open(again[0]).read() == open(paths[0]).read()
    sampled = render.render(str(stopped_run), seed=1, tasks=[1], out_dir=str(tmp_path / "c"),
                            print_fn=lambda line: None)
    assert _frames(open(sampled[0]).read()) != _frames(open(paths[0]).read())


@pytest.mark.parametrize("kwargs, message", [
    ({"methods_": ["comps"]}, "--method comps: not a method of this run; its methods: ppo_tl"),
    ({"seed": 2}, r"--seed 2: the run's seeds are 0\.\.1"),
    ({"tasks": [4]}, r"--tasks 4: tasks are numbered 1\.\.3"),
])
def test_render_refuses_what_the_run_does_not_have(render, stopped_run, kwargs, message):
    with pytest.raises(experiment.RunError, match=message):
        render.render(str(stopped_run), **kwargs)


def test_render_without_a_checkpoint_or_run(render, tmp_path, runner):
    with pytest.raises(experiment.RunError, match="no run.json"):
        render.render(str(tmp_path))
    described = runner.description_of(TINY + ["--out", str(tmp_path / "new")])
    rundir.open_run_dir(str(tmp_path / "new"), described, False)
    with pytest.raises(experiment.RunError, match="ppo_tl has no checkpoint yet"):
        render.render(str(tmp_path / "new"))
