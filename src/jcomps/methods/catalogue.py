"""The methods jcomps ships, registered by name (the package docstring lists them), and the paper's ablation
ladder over them (``LADDER``)."""

from __future__ import annotations

import dataclasses

from jcomps.methods import comps, maml_tl, pearl, pnc, ppo_tl
from jcomps.methods.registry import EVERY_FAMILY, REGISTRY, Registered
from jcomps.training import meta, ppo

# Whether the inner step's advantages are standardised per task (GMPS's ``center_adv``) is one choice for the whole
# ladder, so that no rung changes it: the rung that adds importance sampling changes only the weights and the
# baseline (docs/log.md, "The ablation ladder: one feature per rung", has both readings measured).
STANDARDISED_INNER_ADVANTAGES = False
_META = meta.MetaConfig(normalize_advantages=STANDARDISED_INNER_ADVANTAGES)
_NO_IS = dataclasses.replace(_META, importance_sampling=False, vtrace_baseline=False)
_VANILLA_PG = {"num_updates": 1, "minibatch_size": 0, "surrogate": "vanilla"}
# GMPS's RL step calibrated on Point Goal (docs/families.md, "GMPS's vanilla policy gradient on Point Goal"): no
# learning rate solves task 1 at the family's reward scale of 0.1, 3e-3 is the best at 1. Its meta step stays the
# other rungs' (rewards × 0.1, inner learning rate 0.05: the paper's α = 0.005 on raw rewards): in the RL step's
# units its value heads, copies of a critic that does not fit at scale 1, leave advantages of |A| 50-100 and the
# inner step diverges (the BC loss is infinite from task 2 on, every outer update skipped); in the family's units a
# copied critic is 10x off, so its heads start afresh and fit (EV 0.8; docs/families.md has the three readings).
_GMPS_FAMILY_SETTINGS = {EVERY_FAMILY: {"ppo": _VANILLA_PG},
                         "point_goal": {"ppo": {"reward_scale": 1.0, "learning_rate": 3e-3},
                                        "meta": {"reward_scale": 0.1, "value_init": "random"}}}

REGISTRY.update({
    "ppo_tl": Registered(ppo_tl.PPOTLConfig(), ppo_tl.make),
    "ppo": Registered(ppo_tl.PPOTLConfig(), ppo_tl.make_scratch),
    "comps": Registered(comps.CoMPSConfig(meta=_META), comps.make),
    "gmps": Registered(comps.CoMPSConfig(ppo=dataclasses.replace(ppo.PPOConfig(), **_VANILLA_PG), meta=_NO_IS,
                                         warm_start=False), comps.named("gmps"), _GMPS_FAMILY_SETTINGS),
    "gmps_ppo": Registered(comps.CoMPSConfig(meta=_NO_IS, warm_start=False), comps.named("gmps_ppo")),
    "gmps_ppo_is": Registered(comps.CoMPSConfig(meta=_META, warm_start=False), comps.named("gmps_ppo_is")),
    "gmps_ppo_last": Registered(comps.CoMPSConfig(meta=_NO_IS, warm_start=False, meta_start="last"),
                                comps.named("gmps_ppo_last")),
    "gmps_ppo_is_last": Registered(comps.CoMPSConfig(meta=_META, warm_start=False, meta_start="last"),
                                   comps.named("gmps_ppo_is_last")),
    "gmps_ppo_is_x2": Registered(comps.CoMPSConfig(meta=_META, warm_start=False, num_skilled=40),
                                 comps.named("gmps_ppo_is_x2")),
    "maml_tl": Registered(maml_tl.MAMLTLConfig(), maml_tl.make),
    "pnc": Registered(pnc.PNCConfig(), pnc.make,
                      {EVERY_FAMILY: {"ppo": {"hidden_sizes": pnc.PNCConfig().ppo.hidden_sizes}}}),
    "pearl": Registered(pearl.PEARLConfig(), pearl.make),
})

# The paper's ablation ladder (appendix "CoMPS Ablation"): (lower rung, upper rung, the feature the upper adds).
# Every pair differs in the config fields of its feature and in nothing else (tested).
LADDER_FEATURES: dict[str, tuple[str, ...]] = {
    # The RL step and its calibration (a rung's RL step is tuned for it, as the paper tuned each method; where that
    # moves its reward units the meta step keeps the other rungs' units and cannot copy the RL step's critic).
    "PPO as the RL step": ("ppo.num_updates", "ppo.minibatch_size", "ppo.surrogate", "ppo.reward_scale",
                           "ppo.learning_rate", "meta.reward_scale", "meta.value_init"),
    "importance-sampled inner step with the V-trace baseline": ("meta.importance_sampling", "meta.vtrace_baseline"),
    "skilled data x2": ("num_skilled",),
    "FTML warm start": ("warm_start",),
}
LADDER: tuple[tuple[str, str, str], ...] = (
    ("gmps", "gmps_ppo", "PPO as the RL step"),
    ("gmps_ppo", "gmps_ppo_is", "importance-sampled inner step with the V-trace baseline"),
    ("gmps_ppo_is", "gmps_ppo_is_x2", "skilled data x2"),
    ("gmps_ppo_is", "comps", "FTML warm start"),
)

METHODS = tuple(REGISTRY)
"""The methods jcomps ships (``names()`` also lists any registered since)."""
