"""CPU host devices: the environment for N devices, and that batched LAPACK kernels on them do not deadlock."""

import subprocess
import sys
import textwrap

import pytest

from jcomps.runner import hostdevices


def test_environment_sets_the_device_count_and_a_pool_larger_than_the_cores():
    env = hostdevices.environment(2, {"XLA_FLAGS": "--xla_cpu_enable_fast_math=false "
                                                   "--xla_force_host_platform_device_count=8", "PATH": "/bin"})
    assert env["XLA_FLAGS"].split() == ["--xla_cpu_enable_fast_math=false", "--xla_force_host_platform_device_count=2"]
    assert int(env["NPROC"]) == hostdevices.cores() + 2
    assert env["PATH"] == "/bin"


def test_environment_keeps_a_pool_size_the_user_chose():
    assert hostdevices.environment(2, {"NPROC": "7"})["NPROC"] == "7"
    assert "NPROC" not in hostdevices.environment(2, {"PORTABLE_NPROC": "7"})


@pytest.mark.parametrize("bad", [0, -1, 1.5, "2", True])
def test_environment_rejects_a_bad_device_count(bad):
    with pytest.raises(ValueError, match="devices must be an integer >= 1"):
        hostdevices.environment(bad, {})


def test_configure_after_jax_started_is_an_error():
    import jax

    jax.numpy.zeros(1).block_until_ready()
    with pytest.raises(RuntimeError, match="before JAX starts"):
        hostdevices.configure(2)


def test_batched_initialisation_on_two_host_devices_finishes():
    """PPO+TL's initialisation (orthogonal initialisers) under vmap, sharded over 2 host devices with 2 seeds each:
    jaxlib's batched QR waits on XLA:CPU's intra-op pool from a pool thread. Without ``configure``'s pool size
    this hung every time on a 2-core machine (jax 0.10.2, 5 of 5 tries); the subprocess has a timeout so that a
    regression fails instead of hanging."""
    child = textwrap.dedent("""
        from jcomps.runner import hostdevices
        hostdevices.configure(2)
        import jax, jax.numpy as jnp
        from jax.sharding import NamedSharding, PartitionSpec as P
        from jcomps import envs, methods
        init = methods.make("ppo_tl", envs.make("point_goal")).init
        mesh = jax.make_mesh((2,), ("seed",), devices=jax.devices()[:2])
        f = jax.jit(jax.shard_map(jax.vmap(init), mesh=mesh, in_specs=P("seed"), out_specs=P("seed"),
                                  check_vma=False))
        keys = jax.device_put(jax.random.split(jax.random.PRNGKey(0), 4), NamedSharding(mesh, P("seed")))
        for _ in range(3):
            state = jax.block_until_ready(f(keys))
        print(jax.device_count(), state.task_index.shape)
    """)
    out = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, timeout=240)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split("\n")[0] == "2 (4,)"
