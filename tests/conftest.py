"""Shared test settings.

Hypothesis: no deadline (the first example of a property pays for JAX's op compilation, which is not a bug) and
few examples, so the suite stays fast on a 2-core CPU. ``HYPOTHESIS_PROFILE=thorough`` runs many more.

Matrix products run at full float32 precision: on GPUs JAX's default is TF32 (about 3 significant digits), which
fails the tests that compare two computations of the same gradient at float32 tolerances (seen on an H100 with
jax 0.11.2; with ``highest`` the meta, V-trace and CoMPS tests pass there). On CPU this changes nothing.

JAX sees two CPU host devices (set through ``jcomps.runner.hostdevices`` before JAX starts, with its deadlock-free
thread pool), so the runner's sharding of seeds over devices is tested in-process.

The runner's persistent compile cache is off in tests (``JCOMPS_COMPILE_CACHE=none``, unless set otherwise), so
the suite writes nothing under the user's cache home and every run compiles what it tests;
``tests/test_compile_cache.py`` tests the cache in directories of its own.

Programs compile with most of XLA's optimisation off (``JAX_DISABLE_MOST_OPTIMIZATIONS=1`` unless set otherwise,
inherited by the processes the tests start): compiling dominates the suite's time and the tests' programs are
tiny, so this cuts the suite's time by a third to a half on 2 cores (19m01 to 9m30 measured back to back; one
file, the two ways back to back at another hour, 30–45%). It changes which float operations are fused, not what
a program computes; ``tests/test_envs.py`` compiles its MJX rollouts fully optimised, as users run
them, because its batched-against-unbatched tolerance was measured so. ``JAX_DISABLE_MOST_OPTIMIZATIONS=0`` runs the
whole suite optimised (it passes that way too).
"""

import importlib.util
import os
import pathlib

from jcomps.runner import hostdevices

os.environ.setdefault("JCOMPS_COMPILE_CACHE", "none")
os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")  # JAX reads it (its own parsing) when imported below

if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    hostdevices.configure(2)

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from hypothesis import settings  # noqa: E402

jax.config.update("jax_default_matmul_precision", "highest")

settings.register_profile("fast", deadline=None, max_examples=25)
settings.register_profile("thorough", deadline=None, max_examples=500)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "fast"))


def _load_script(name: str, folder: str = "experiments"):
    """``<folder>/<name>.py`` loaded as a module."""
    path = pathlib.Path(__file__).resolve().parents[1] / folder / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _script_fixture(fixture_name: str, script: str, doc: str, folder: str = "experiments"):
    """A session fixture ``fixture_name``: ``<folder>/<script>.py`` loaded as a module."""
    def fixture():
        return _load_script(script, folder)

    fixture.__doc__ = doc
    return pytest.fixture(scope="session", name=fixture_name)(fixture)


def _check_meta_gradient(loss, grad, params, policy_of, eps: float, rtol: float, first_order: bool):
    """The meta-gradient ``grad`` (a pytree like ``params``) against central finite differences of ``loss`` along a
    random direction. The observation statistics (``policy_of(tree)["obs_norm"]``) are data, not parameters (no
    gradient by design), so the direction holds them fixed. Second order, the two must agree to ``rtol``; first
    order drops the inner step's curvature, so they must not (by more than 1e-3 relative)."""
    rng = np.random.default_rng(3)
    direction = jax.tree.map(lambda x: jnp.asarray(rng.normal(size=x.shape)), params)
    policy_of(direction)["obs_norm"] = jax.tree.map(jnp.zeros_like, policy_of(direction)["obs_norm"])
    shift = lambda s: jax.tree.map(lambda p, d: p + s * eps * d, params, direction)  # noqa: E731
    numeric = (loss(shift(1.0)) - loss(shift(-1.0))) / (2 * eps)
    analytic = sum(jnp.vdot(g, d) for g, d in zip(jax.tree.leaves(grad), jax.tree.leaves(direction)))
    if first_order:
        assert abs(float(analytic) - float(numeric)) > 1e-3 * abs(float(numeric))
    else:
        np.testing.assert_allclose(float(analytic), float(numeric), rtol=rtol)


@pytest.fixture(scope="session")
def check_meta_gradient():
    """``check(loss, grad, params, policy_of, eps, rtol, first_order)``: a meta-gradient against finite
    differences (test_meta, test_baselines)."""
    return _check_meta_gradient


def _kill_and_resume(runner, argv: list, out: pathlib.Path, killed, full: pathlib.Path) -> None:
    """Runs ``argv`` into ``out`` with each method in ``killed`` stopped after its first chunk (its checkpoint 1 is
    all there is), resumes the run with ``--resume``, and asserts that every method's raw results equal those of
    the uninterrupted run in ``full``, array for array (wall time apart)."""
    from jcomps.runner import experiment, results, rundir

    run = runner.describe(runner.parse_args(argv + ["--out", str(out)]))
    rundir.open_run_dir(str(out), run, resume=False)
    for name in killed:
        assert experiment.run_method(str(out), name, run, resume=False, programs=runner.PROGRAMS,
                                     stop_after_chunks=1) is None
        assert sorted(os.listdir(out / "checkpoints" / name)) == ["1"]
        # What it finished is reportable before the resume: the uninterrupted run's first chunk, array for array.
        done = results.load_partial(str(out), name)
        chunk = min(run.run.chunk_tasks, run.run.num_tasks)
        first = results.truncate(results.load(str(full), name), chunk)
        assert results.tasks_done(done) == chunk
        for a, b in zip(jax.tree.leaves(first._replace(seconds=0.0)), jax.tree.leaves(done._replace(seconds=0.0))):
            np.testing.assert_array_equal(a, b, err_msg=f"{name} partial")
    runner.main(["--out", str(out), "--resume"])
    for name in run.run.methods:
        assert results.load_partial(str(out), name) is None  # a finished entry keeps no partial results
        with np.load(full / "raw" / f"{name}.npz") as fa, np.load(out / "raw" / f"{name}.npz") as fb:
            assert fa.files == fb.files
            for key in fa.files:
                if key != "seconds":
                    np.testing.assert_array_equal(fa[key], fb[key], err_msg=f"{name} {key}")


@pytest.fixture(scope="session")
def kill_and_resume():
    """``check(runner, argv, out, killed, full)``: a run "killed" after the first chunk of the methods ``killed``
    and resumed equals the uninterrupted run ``full`` (test_experiment, test_baselines, test_pearl)."""
    return _kill_and_resume


@pytest.fixture(scope="session")
def tiny_run(runner, tmp_path_factory):
    """``run(argv, name)``: the runner run with ``argv`` into a fresh ``<name>/full`` directory, which it returns
    (the module fixtures of tiny end-to-end runs: test_experiment, test_baselines, test_pearl, test_metaworld)."""
    def run(argv: list, name: str) -> pathlib.Path:
        out = tmp_path_factory.mktemp(name) / "full"
        runner.main(argv + ["--out", str(out)])
        return out

    return run


@pytest.fixture(scope="session")
def console():
    """The runner's progress lines and TensorBoard logs (``jcomps.console``)."""
    from jcomps import console as module

    return module
runner = _script_fixture("runner", "run_sequence", "The runner (its ``parse_args`` and ``main``).")
merge_runs = _script_fixture("merge_runs", "merge_runs", "Merging runs (its ``merge``).")
render = _script_fixture("render", "render", "Policy replays (its ``render``).")
reproduce = _script_fixture("reproduce", "reproduce", "A family's experiments of the paper (its ``main``).")
report_script = _script_fixture("report_script", "report", "Regenerating a run directory's report (its ``main``).")
plot_cells = _script_fixture("plot_cells", "plot_cells", "The figure of several run directories (its ``main``).",
                             folder="scripts")


# The runner's tiny end-to-end run, shared by the tests of the host loop and of the run directory
# (test_experiment, test_rundir): every method at its smallest, comps and ppo_tl on 3 tasks, 2 seeds, a checkpoint
# after every task.
_TINY = ["--budget", "3", "--num-trajectories", "2", "--hidden-sizes", "8", "--num-updates", "1",
         "--minibatch-size", "16", "--num-meta-steps", "1", "--num-outer-steps", "2", "--inner-trajectories", "2",
         "--skilled-trajectories", "2", "--num-skilled", "2", "--num-offpolicy", "4", "--heldout-iterations", "1",
         "--heldout-budget", "3", "--backward-tasks", "2"]
_RUN = ["--methods", "comps", "ppo_tl", "--num-tasks", "3", "--seeds", "2", "--chunk-tasks", "1"]


@pytest.fixture(scope="session")
def tiny_options():
    """Runner options that make every method as small as it goes (command-line arguments)."""
    return list(_TINY)


@pytest.fixture(scope="session")
def full_run_argv(tiny_options):
    """The options of ``full_run``: ``tiny_options``, then comps and ppo_tl on 3 tasks, 2 seeds, chunks of 1 task."""
    return tiny_options + _RUN


@pytest.fixture(scope="session")
def full_run(tiny_run, full_run_argv):
    """An uninterrupted run of ``full_run_argv`` (compiles the programs that the other tests reuse, through the
    runner's ``PROGRAMS``); tests may resume it or copy it, never change what it holds."""
    return tiny_run(full_run_argv, "runs")
