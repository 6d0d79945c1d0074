"""Shared test settings.

Hypothesis: no deadline (the first example of a property pays for JAX's op compilation, which is not a bug) and
few examples, so the suite stays fast on a 2-core CPU. ``HYPOTHESIS_PROFILE=thorough`` runs many more.

Matrix products run at full float32 precision: on GPUs JAX's default is TF32 (about 3 significant digits), which
fails the tests that compare two computations of the same gradient at float32 tolerances (seen on an H100 with
jax 0.11.2; with ``highest`` the meta, V-trace and CoMPS tests pass there). On CPU this changes nothing.

JAX sees two CPU host devices (set through ``jcomps.hostdevices`` before JAX starts, with its deadlock-free
thread pool), so the runner's sharding of seeds over devices is tested in-process.
"""

import importlib.util
import os
import pathlib

from jcomps import hostdevices

if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    hostdevices.configure(2)

import jax  # noqa: E402
import pytest  # noqa: E402
from hypothesis import settings  # noqa: E402

jax.config.update("jax_default_matmul_precision", "highest")

settings.register_profile("fast", deadline=None, max_examples=25)
settings.register_profile("thorough", deadline=None, max_examples=500)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "fast"))


def _load_script(name: str):
    """``experiments/<name>.py`` loaded as a module."""
    path = pathlib.Path(__file__).resolve().parents[1] / "experiments" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="session")
def console():
    """``experiments/progress.py`` (the runner's progress lines and TensorBoard) loaded as a module."""
    return _load_script("progress")


@pytest.fixture(scope="session")
def runner():
    """``experiments/run_sequence.py`` loaded as a module (its ``parse_args`` and ``main``)."""
    return _load_script("run_sequence")


@pytest.fixture(scope="session")
def merge_runs():
    """``experiments/merge_runs.py`` loaded as a module (its ``merge``)."""
    return _load_script("merge_runs")


@pytest.fixture(scope="session")
def render():
    """``experiments/render.py`` loaded as a module (its ``render``)."""
    return _load_script("render")
