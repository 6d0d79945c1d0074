"""docs/extending.md, run: its family and its method are registered from the page's own code and run through the
runner, so the page cannot drift from the code."""

import pathlib
import re
import sys
import types

import chex
import jax
import numpy as np
import pytest

from jcomps import envs, methods
from jcomps.analysis import report
from jcomps.runner import results

DOC = pathlib.Path(__file__).resolve().parents[1] / "docs" / "extending.md"


def _blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)


@pytest.fixture(scope="module")
def page():
    """The namespace of the page's first two code blocks (the family and the method, registered once), run as the
    body of a module, as a user's file would be."""
    family_code, method_code, _, _ = _blocks()
    module = types.ModuleType("extending_example")
    sys.modules[module.__name__] = module
    exec(compile(family_code, f"{DOC}:family", "exec"), module.__dict__)
    exec(compile(method_code, f"{DOC}:method", "exec"), module.__dict__)
    return dict(module.__dict__)


@pytest.fixture(scope="module")
def run(page, tmp_path_factory):
    """The page's third block: both methods on the new family through the runner, then the report."""
    out = str(tmp_path_factory.mktemp("extending"))
    namespace = {**page, "OUT": out}
    exec(compile(_blocks()[2], f"{DOC}:run", "exec"), namespace)
    report.write(out)
    return out, namespace["raws"], namespace["configs"]


def test_the_page_has_a_family_a_method_a_run_and_a_method_without_ppo():
    family, method, run, without_ppo = _blocks()  # exactly four blocks, in this order
    assert "envs.register(" in family and "methods.register(" not in family
    assert "methods.register(" in method and "envs.register(" not in method
    assert "experiment.run(" in run and "register(" not in run
    # the method without PPO brings its own held-out meta-test and has no PPO config
    assert "methods.register(" in without_ppo and "adapt=adapt" in without_ppo and "PPOConfig" not in without_ppo


def test_a_registered_family_is_found_and_runs_through_the_runner(page, run):
    out, raws, configs = run
    family = envs.make("line_goal")
    assert "line_goal" in envs.names() and family is envs.make("line_goal")
    assert envs.sequence_values("line_goal", num_tasks=3).tolist() == [1.0, -1.0, 0.5]
    with pytest.raises(ValueError, match="goal position in m"):
        family.tasks([5.0])
    # Its calibrated settings reach every method's default config, and its held-out budget the evaluations.
    assert methods.default_config("ppo_tl", "line_goal").ppo.normalize_observations is False
    assert configs["ppo_tl"].ppo.budget == 10
    raw = results.load(out, "ppo_tl")
    assert raw.per_task.task.iterations.shape == (2, 2)
    assert np.all((raw.per_task.task.iterations >= 1) & (raw.per_task.task.iterations <= 10))
    assert raw.measured.heldout.mean_return.shape[:3] == (2, 2, 2)  # seeds, held-out columns (0 and 2 tasks), tasks
    assert (pathlib.Path(out) / "results.json").is_file()


def test_a_registered_method_runs_through_the_runner_and_starts_each_task_with_a_fresh_critic(page, run):
    out, raws, configs = run
    assert "ppo_fresh_critic" in methods.names()
    raw = raws["ppo_fresh_critic"]
    assert raw.per_task.task.iterations.shape == (2, 2) and np.all(raw.per_task.task.iterations >= 1)
    assert np.isfinite(raw.per_task.task.per_iteration.mean_return).all()
    assert "ppo_fresh_critic" in (pathlib.Path(out) / "significance.md").read_text()
    # The law of the method: each task starts from the learnt policy and the initial critic.
    family = envs.make("line_goal")
    method = methods.make("ppo_fresh_critic", family, configs["ppo_fresh_critic"])
    state = method.init(jax.random.PRNGKey(0))
    task = envs.task_at(family, 0)
    learn = jax.jit(method.learn_task)
    learnt, metrics = learn(state, task)
    # Whatever critic the state carries, the task is learnt from the initial one: the same result.
    carried = state._replace(params=state.params._replace(value=jax.tree.map(lambda x: x + 1.0, state.params.value)))
    again, metrics_again = learn(carried, task)
    chex.assert_trees_all_equal((learnt.params, metrics), (again.params, metrics_again))
    assert jax.tree.leaves(learnt.params.value)[0].shape == jax.tree.leaves(state.fresh.value)[0].shape
    changed = [not np.array_equal(a, b) for a, b in zip(jax.tree.leaves(learnt.params.value),
                                                          jax.tree.leaves(state.fresh.value))]
    assert any(changed)  # the critic trained on the task ...
    np.testing.assert_array_equal(jax.tree.leaves(learnt.fresh.value)[0], jax.tree.leaves(state.fresh.value)[0])


def test_the_readme_shows_the_quickstart_as_it_is():
    """The README's Python example is examples/quickstart.py, verbatim (the file is what a user runs)."""
    root = DOC.parents[1]
    readme = (root / "README.md").read_text()
    quickstart = (root / "examples" / "quickstart.py").read_text()
    assert quickstart.strip() in [b.strip() for b in re.findall(r"```python\n(.*?)```", readme, flags=re.S)]


def test_a_method_without_ppo_must_bring_its_own_held_out_meta_test(monkeypatch):
    """The held-out meta-test adapts with the method's PPO config; a method with none and no ``adapt`` is refused
    by name when it is made, not deep inside a run (it used to fail reading ``config.ppo`` in continual.py)."""
    import dataclasses

    @dataclasses.dataclass(frozen=True)
    class NoPPOConfig:
        learning_rate: float = 0.1

    def make(family, config, progress_fn):
        return methods.Method("no_ppo", config, family, init=lambda rng: None, learn_task=lambda s, t: (s, None))

    monkeypatch.setitem(methods.REGISTRY, "no_ppo", methods.Registered(NoPPOConfig(), make))
    with pytest.raises(TypeError, match="method 'no_ppo' has no PPO config .*give its Method an `adapt`"):
        methods.make("no_ppo", envs.make("point_goal"))
    adapting = lambda family, config, progress_fn: make(family, config, progress_fn)._replace(  # noqa: E731
        adapt=lambda state, task, rng, iterations: (None, None))
    monkeypatch.setitem(methods.REGISTRY, "no_ppo", methods.Registered(NoPPOConfig(), adapting))
    assert methods.make("no_ppo", envs.make("point_goal")).adapt is not None


@pytest.fixture(scope="module")
def es_run(page, tmp_path_factory):
    """The page's fourth block, a method without PPO, registered, then run through the runner with the held-out
    meta-test on (its own ``adapt``): (run directory, raws, the method's config)."""
    from jcomps import continual
    from jcomps.runner import description, experiment

    namespace = dict(page)
    exec(compile(_blocks()[3], f"{DOC}:es", "exec"), namespace)
    config = namespace["ESConfig"](budget=20)
    run = description.RunConfig(family="line_goal", methods=("es_tl",), seeds=2, num_tasks=2, chunk_tasks=1)
    out = str(tmp_path_factory.mktemp("es") / "run")
    described = description.describe(run, continual.EvalConfig(backward_tasks=1, heldout_iterations=2),
                                      {"es_tl": config})
    raws = experiment.run(out, described)
    report.write(out)
    return out, raws, config


def test_a_method_without_ppo_runs_through_the_runner_with_its_own_meta_test(es_run):
    out, raws, config = es_run
    raw = raws["es_tl"]
    its = raw.per_task.task.iterations
    assert its.shape == (2, 2) and np.all((its >= 1) & (its <= 20))
    valid = raw.per_task.task.per_iteration.valid
    returns = raw.per_task.task.per_iteration.mean_return
    # ES learns: on every task of every seed, the last iteration's return is above the first's.
    last = np.take_along_axis(returns, (its - 1)[..., None].astype(int), axis=2)[..., 0]
    assert np.all(last > returns[..., 0]), (returns[..., 0], last)
    assert np.all(valid.sum(axis=2) == its)
    # The held-out meta-test ran ES's own adapt (it has no PPO config): a curve of 3 points per held-out task at each
    # of the 3 measurements (before the first task, after each chunk).
    assert raw.measured.heldout.mean_return.shape[:4] == (2, 3, 2, 3)
    assert np.isfinite(raw.measured.heldout.mean_return).all()
    assert "es_tl" in (pathlib.Path(out) / "significance.md").read_text()
    with pytest.raises(ValueError, match="num_trajectories=3; allowed: an even integer >= 2"):
        type(config)(num_trajectories=3)
