"""Task families and their task sequences, found through one registry.

Families, by the names used everywhere (CLI included): ``point_goal``, ``cheetah_vel``, ``ant_goal``, ``ant_dir``,
``metaworld``; ``register`` adds one (docs/extending.md).

>>> fam = make("point_goal")
>>> tasks = sequence(fam, "non-stationary", num_tasks=5)   # stacked task pytree, leading axis 5

A family is registered with its **calibrated settings**: the defaults it gives the parts of a method's config, by
part (``"ppo"``: ``PPOConfig``, the RL step of every PPO-based method; ``"meta"``: ``MetaConfig``, the meta step;
``"pearl"``: ``PEARLConfig``; a config class names its part in ``SETTINGS_PART``; ``"eval"``: ``EvalConfig``'s
family defaults, ``EvalConfig.resolve``). ``jcomps.methods.default_config``
puts them over a method's registered defaults. They are registered beside the family, not inside it, so that a
report or a config can be built without constructing a family (MuJoCo's and MetaWorld's import heavy libraries).
"""

from jcomps.envs.base import EnvState, Family, strong, validate_values
from jcomps.envs.catalogue import FAMILIES
from jcomps.envs.registry import Registered, Settings, make, names, register, settings, settings_by_field
from jcomps.envs.sequences import SEQUENCE_KINDS, held_out, sequence, sequence_values, task_at

__all__ = [
    "EnvState", "FAMILIES", "Family", "Registered", "SEQUENCE_KINDS", "Settings", "held_out", "make", "names",
    "register", "sequence", "sequence_values", "settings", "settings_by_field", "strong", "task_at", "validate_values",
]
