"""Shared test settings.

Hypothesis: no deadline (the first example of a property pays for JAX's op compilation, which is not a bug) and
few examples, so the suite stays fast on a 2-core CPU. ``HYPOTHESIS_PROFILE=thorough`` runs many more.
"""

import os


from hypothesis import settings

settings.register_profile("fast", deadline=None, max_examples=25)
settings.register_profile("thorough", deadline=None, max_examples=500)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "fast"))
