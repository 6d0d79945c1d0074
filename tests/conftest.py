"""Shared test settings.

Hypothesis: no deadline (the first example of a property pays for JAX's op compilation, which is not a bug) and
few examples, so the suite stays fast on a 2-core CPU. ``HYPOTHESIS_PROFILE=thorough`` runs many more.

JAX sees two CPU devices (set before JAX is imported), so the runner's sharding of seeds over devices is tested.
"""

import os

if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip()

from hypothesis import settings

settings.register_profile("fast", deadline=None, max_examples=25)
settings.register_profile("thorough", deadline=None, max_examples=500)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "fast"))
