"""What the CoMPS paper (Berseth et al., ICLR 2022; ``../shared/paper/comps-paper.tex``) reports, as data: its
protocol, its two p-value tables and the claims a reproduction checks. Line numbers ("L562") are the source's.

The paper's figures are referred to by the published PDF's numbers, as docs/results.md does: Figure 3 is the
stationary iterations-to-success figure (``fig:comparison-random-seq``, L549), Figure 4 the non-stationary
lifelong return (``fig:comparison-avg-ret``, L569); the non-stationary iterations to success are in the appendix
(``fig:comparison-fixed-seq-itr``, L784).
"""

from __future__ import annotations

from typing import NamedTuple, Optional

FAMILIES = {"cheetah_vel": "Cheetah", "ant_goal": "Ant Goal", "ant_dir": "Ant Direction", "metaworld": "MetaWorld"}
"""Our families that the paper ran, by the paper's column names."""

METHODS = ("comps", "ppo_tl", "gmps_ppo", "maml_tl", "pnc", "pearl")
"""The methods of the paper's comparisons (L536, L587, L591)."""

ABLATION = ("gmps", "gmps_ppo_is", "gmps_ppo_is_x2")
"""The rungs of the appendix's ablation (L867) that the comparisons do not run (GMPS+PPO and CoMPS are in both)."""

SEEDS = 6
"""Seeds per method (L753, L812, every caption)."""

NUM_TASKS = 40
"""Tasks per sequence: 40 in the text (L561, "each of 40 tasks") and every caption but one (L575, L746, L777, L805;
L782: "6 x number of tasks = 240"); the stationary figure's caption says 20 (L555). We run 40 on both sequences
(MetaWorld's list has 39)."""

TEST = ("two-sided independent t-test (CoMPS, Alg) using a bootstrap of 30,000 over 6 randomly seeded trials "
        "(L753, L812); one p-value per cell")

QUANTITY = {"stationary": "iterations", "non-stationary": "mean_return"}
"""What each table tests: on the stationary sequences "the distribution of average number of episodes needed to
complete a task" (L753), on the non-stationary ones "the distribution of average reward" (L812)."""

# tab:res-stat-sig (L755-767) and tab:res-stat-sig-ns (L814-826), copied from the source; GMPS+PPO and the
# ablation are in neither.
P_VALUES = {
    "stationary": {
        "ant_goal": {"pearl": 1.85e-11, "ppo_tl": 4.54e-11, "maml_tl": 1.12e-11, "pnc": 0.01833026502},
        "cheetah_vel": {"pearl": 0.0002371241398, "ppo_tl": 2.66e-05, "maml_tl": 4.17e-18, "pnc": 0.002410406845},
        "ant_dir": {"pearl": 7.36e-09, "ppo_tl": 0.01990761802, "maml_tl": 1.87e-08, "pnc": 6.35e-09},
        "metaworld": {"pearl": 2.26e-13, "ppo_tl": 0.006441451648, "maml_tl": 0.007026979433, "pnc": 1.26e-10},
    },
    "non-stationary": {
        "ant_goal": {"ppo_tl": 0.0003071245518, "pnc": 0.0002119448748, "maml_tl": 0.0001044653709,
                     "pearl": 0.0001308992933},
        "cheetah_vel": {"ppo_tl": 7.32e-08, "pnc": 3.93e-08, "maml_tl": 7.91e-08, "pearl": 1.39e-06},
        "ant_dir": {"ppo_tl": 0.2102584056, "pnc": 0.07235237317, "maml_tl": 0.01082454019, "pearl": 0.02516455006},
        "metaworld": {"ppo_tl": 0.9973906496, "pnc": 1.49e-05, "maml_tl": 8.97e-06, "pearl": 9.79e-06},
    },
}


def p_value(sequence: str, family: str, method: str):
    """The paper's p-value of CoMPS against ``method`` on ``family``'s ``sequence`` (None where it gives none)."""
    return P_VALUES.get(sequence, {}).get(family, {}).get(method)


class Claim(NamedTuple):
    """What the paper says of one check of a reproduction on some sequences and families: a claim it makes there,
    or (``made`` False) what it says instead where it does not make the claim.

    Attributes:
      key: the check's name in reports; several entries share it where the paper's words differ by sequence or
        family.
      text: the claim, or what the paper says instead, in the paper's words where it has them.
      where: the source lines.
      sequences: the sequences it is said of.
      families: the families it is said of (empty: every family).
      made: whether the paper makes the claim there.
      quantity: what the check compares CoMPS with the other methods on, where it can compare either:
        ``iterations`` (to success) or ``mean_return`` (the average return during the tasks' RL steps).
    """

    key: str
    text: str
    where: str
    sequences: tuple
    families: tuple = ()
    made: bool = True
    quantity: Optional[str] = None


_BOTH = ("stationary", "non-stationary")

CLAIMS = (
    Claim("fastest", "CoMPS \"solves all of the tasks the fastest\"", "L562-563", ("stationary",),
          quantity="iterations"),
    Claim("fastest", "CoMPS \"solves all of the tasks the fastest\" is said of the stationary sequences; of the "
          "non-stationary ones the paper says it \"solves most tasks faster than other methods\"", "L562-563, L790",
          ("non-stationary",), made=False, quantity="iterations"),
    Claim("faster_with_tasks", "CoMPS \"solves tasks faster as more tasks are experienced\"", "L563, L596", _BOTH),
    Claim("ahead_of_gmps_ppo", "GMPS+PPO \"performs worse than CoMPS, especially on Ant Goal and Ant Direction\" "
          "(the iterations of Figure 3)", "L591", ("stationary",), quantity="iterations"),
    Claim("ahead_of_gmps_ppo", "GMPS+PPO is among \"the best performing methods\" on MetaWorld, but CoMPS \"reaches "
          "these rewards in fewer iterations compared to PPO+TL and GMPS+PPO\"", "L587", ("non-stationary",),
          ("metaworld",), quantity="iterations"),
    Claim("ahead_of_gmps_ppo", "GMPS+PPO \"achieves some of the lowest returns across all methods\"", "L782",
          ("non-stationary",), quantity="mean_return"),
    Claim("highest_return", "CoMPS \"achieves higher average reward while completing the tasks\"",
          "L565, L738, L746", ("stationary",), quantity="mean_return"),
    Claim("highest_return", "CoMPS's higher rewards than every other method are not claimed on Ant Direction and "
          "MetaWorld: there the paper finds PPO+TL \"somewhat similar\" and \"very similar to CoMPS\" (its p 0.21 "
          "and 0.997)", "L812", ("non-stationary",), ("ant_dir", "metaworld"), made=False, quantity="mean_return"),
    Claim("highest_return", "CoMPS \"still attains higher rewards than other methods\" on Half-Cheetah (the "
          "non-stationary table tests the average reward)", "L584, L812", ("non-stationary",), ("cheetah_vel",),
          quantity="mean_return"),
    Claim("highest_return", "CoMPS \"achieves higher average returns\", \"a median average return that is higher "
          "than all other methods\" (the non-stationary table tests the average reward)", "L577, L782, L812",
          ("non-stationary",), quantity="mean_return"),
    Claim("backward_transfer", "CoMPS shows \"strong\" backward transfer on Ant Direction, Ant Goal and Cheetah",
          "L566, L848", _BOTH, ("ant_goal", "ant_dir", "cheetah_vel")),
    Claim("backward_transfer", "CoMPS's \"strong\" backward transfer is said of Ant Direction, Ant Goal and Cheetah; "
          "on MetaWorld the paper says it \"reduces as more tasks are seen\"", "L848-849", _BOTH, ("metaworld",),
          made=False),
)
"""The checks of a reproduction and what the paper says of each, by sequence and family (``claim`` picks the entry
that applies: the first that names the sequence and the family or every family). A claim of every family applies to
families the paper did not run; a claim of named families is left out of other families' reports."""


def claim(key: str, sequence: str, family: str) -> Optional[Claim]:
    """What the paper says of check ``key`` on ``family``'s ``sequence`` (None where it says nothing)."""
    return next((c for c in CLAIMS if c.key == key and sequence in c.sequences
                 and (not c.families or family in c.families)), None)
