"""A family's experiments of the paper, reproduced: the protocol (methods, sequences, seeds, tasks) at the paper's
scale or a CPU's, and the comparison of a study's results with what the paper reports (``jcomps.analysis.paper``): the
Figure-3 panel (iterations to success per task), the lifelong-return panel, the p-value table beside the
paper's, and the table of the paper's claims with what the study shows for each.

``experiments/reproduce.py`` runs a protocol (each method of each sequence a ``run_sequence.py`` run directory,
merged per sequence) and writes this report; the functions here take the merged ``results.json`` of each sequence.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Optional

import numpy as np

from jcomps import envs, methods
from jcomps.analysis import paper, statistics
from jcomps.numerics import check_field

SCALES = ("cpu", "paper")
SEQUENCES = ("stationary", "non-stationary")
ALPHA = 0.05
"""The significance level of the claims table."""

CPU_METHODS = ("comps", "gmps_ppo", "gmps_ppo_is", "ppo_tl")
CPU_SEEDS = 4
CPU_TASKS = 6
"""The CPU scale: CoMPS, GMPS+PPO, GMPS+PPO+IS (CoMPS without the warm start, its twin in every other field)
and PPO+TL on the first 6 tasks of the non-stationary sequence, 4 seeds, without
the held-out meta-test (on the MuJoCo families it would cost as much as the training): a 2-core machine finishes a
family in hours (docs/results.md has the measured times)."""

BACKWARD_STRONG = 0.5
"""The claims table reads backward transfer (the paper's normalized reward, 1: nothing forgotten, 0: forgotten) as
"strong" from this value up, "weak" between 0 and it, "reversed" at or below 0: our threshold, the paper gives none
(L848 calls what its figure shows "strong")."""


@dataclasses.dataclass(frozen=True)
class Protocol:
    """A family's experiments: every method on every sequence, each run a ``run_sequence.py`` run directory.

    Attributes:
      family: a registered family.
      scale: cpu or paper (what the defaults below came from).
      sequences: the sequences run (stationary, non-stationary).
      methods: the methods run on each; comps first (every table compares it with the others).
      seeds: seeds per method.
      num_tasks: tasks per sequence (a prefix of the family's list).
      heldout_iterations: the held-out meta-test's curve (0: off).
      chunk_tasks: tasks between checkpoints (1: a stopped study loses at most one task per method).
      extra: further ``run_sequence.py`` options given to every run (``--budget 3``, ``--set ...``).
    """

    family: str
    scale: str = "cpu"
    sequences: tuple = ("non-stationary",)
    methods: tuple = CPU_METHODS
    seeds: int = CPU_SEEDS
    num_tasks: int = CPU_TASKS
    heldout_iterations: int = 0
    chunk_tasks: int = 1
    extra: tuple = ()

    def __post_init__(self):
        check_field(self.family in envs.names(), "family", self.family, ", ".join(envs.names()))
        check_field(self.scale in SCALES, "scale", self.scale, ", ".join(SCALES))
        check_field(len(self.sequences) > 0 and all(s in SEQUENCES for s in self.sequences), "sequences",
                    self.sequences, ", ".join(SEQUENCES))
        unknown = [m for m in self.methods if m not in methods.names()]
        check_field(not unknown and len(set(self.methods)) == len(self.methods) and "comps" in self.methods,
                    "methods", self.methods, "distinct registered methods including comps: "
                    + ", ".join(methods.names()))
        check_field(self.seeds >= 2, "seeds", self.seeds, "an integer >= 2 (the t-tests need two per method)")
        available = len(envs.make(self.family).task_values)
        check_field(1 <= self.num_tasks <= available, "num_tasks", self.num_tasks,
                    f"an integer in [1, {available}] ({self.family}'s list)")
        check_field(self.heldout_iterations >= 0, "heldout_iterations", self.heldout_iterations, "an integer >= 0")
        check_field(self.chunk_tasks >= 1, "chunk_tasks", self.chunk_tasks, "an integer >= 1")

    def runs(self) -> list[tuple[str, str]]:
        """(sequence, method) of every run, in the order they run."""
        return [(s, m) for s in self.sequences for m in self.methods]

    def run_directory(self, out: str, sequence: str, method: str) -> str:
        return os.path.join(out, sequence, method)

    def run_options(self, sequence: str, method: str) -> list[str]:
        """The ``run_sequence.py`` options of one run (without ``--out``, ``--devices`` and ``--resume``)."""
        return ["--family", self.family, "--methods", method, "--sequence", sequence, "--seeds", str(self.seeds),
                "--num-tasks", str(self.num_tasks), "--chunk-tasks", str(self.chunk_tasks),
                "--heldout-iterations", str(self.heldout_iterations), *self.extra]

    def to_json(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_json(cls, d: dict) -> "Protocol":
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - fields)
        if unknown:
            raise ValueError(f"unknown protocol field(s) {', '.join(unknown)}")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


def protocol(family: str, scale: str = "cpu", seeds: Optional[int] = None, num_tasks: Optional[int] = None,
             methods_: Optional[list] = None, sequences: Optional[list] = None, ablation: bool = False,
             extra: tuple = ()) -> Protocol:
    """The paper's protocol for ``family`` at ``scale``, with overrides.

    - ``paper``: CoMPS, PPO+TL, GMPS+PPO, MAML+TL, PNC and PEARL (``jcomps.analysis.paper.METHODS``) on both
      sequences, 6 seeds, 40 tasks (the family's list where shorter: MetaWorld's 39), the held-out meta-test's
      5-iteration curve; each family's own budget and calibrated settings (its registered defaults).
    - ``cpu``: CoMPS, GMPS+PPO, GMPS+PPO+IS and PPO+TL on the first 6 non-stationary tasks, 4 seeds, no
      held-out test.

    ``ablation`` adds the ladder's other rungs (GMPS, GMPS+PPO+IS, ×2 skilled data)."""
    check_field(scale in SCALES, "scale", scale, ", ".join(SCALES))
    check_field(family in envs.names(), "family", family, ", ".join(envs.names()))
    if scale == "paper":
        base = dict(sequences=SEQUENCES, methods=paper.METHODS, seeds=paper.SEEDS,
                    num_tasks=min(paper.NUM_TASKS, len(envs.make(family).task_values)), heldout_iterations=5)
    else:
        base = dict(sequences=("non-stationary",), methods=CPU_METHODS, seeds=CPU_SEEDS,
                    num_tasks=min(CPU_TASKS, len(envs.make(family).task_values)), heldout_iterations=0)
    chosen = tuple(methods_) if methods_ else base["methods"]
    if ablation:
        chosen = chosen + tuple(m for m in paper.ABLATION if m not in chosen)
    if "comps" in chosen:
        chosen = ("comps",) + tuple(m for m in chosen if m != "comps")
    return Protocol(family=family, scale=scale, sequences=tuple(sequences) if sequences else base["sequences"],
                    methods=chosen, seeds=seeds if seeds is not None else base["seeds"],
                    num_tasks=num_tasks if num_tasks is not None else base["num_tasks"],
                    heldout_iterations=base["heldout_iterations"], extra=tuple(extra))


# --- the comparison with the paper ------------------------------------------------------------------------------

def _floats(rows) -> np.ndarray:
    return np.array([[np.nan if v is None else v for v in row] for row in rows], np.float64)


def per_seed(results: dict, method: str, quantity: str) -> np.ndarray:
    """f64[S]: each seed's mean over the sequence of ``quantity`` (iterations: iterations-to-success;
    mean_return: the average return during each task's RL step)."""
    m = results["methods"][method]
    key = {"iterations": "iterations_to_success", "mean_return": "mean_return_per_task"}[quantity]
    return np.nanmean(_floats(m[key]), axis=1)


def p_value_table(results: dict, family: str, sequence: str) -> list[dict]:
    """CoMPS against every other method of ``results`` (a sequence's merged results.json), on the quantity the
    paper's table for ``sequence`` tests (``jcomps.analysis.paper.QUANTITY``) and on the other one: one row per method
    with the means, this study's t-test and bootstrap p-values and the paper's p-value (None where it has none)."""
    rows = []
    for method in results["methods"]:
        if method == "comps":
            continue
        row = {"method": method, "paper_p": paper.p_value(sequence, family, method)}
        for quantity in ("iterations", "mean_return"):
            sig = statistics.significance(per_seed(results, "comps", quantity), per_seed(results, method, quantity))
            row[quantity] = {k: sig[k] for k in ("mean_a", "mean_b", "t", "p_ttest", "p_bootstrap")}
        row["quantity"] = paper.QUANTITY[sequence]
        rows.append(row)
    return rows


def _significant(p: Optional[float]) -> bool:
    """p < ALPHA. None (no test: fewer than two seeds) is not significant; 0.0 (two constant groups apart) is."""
    return p is not None and bool(np.isfinite(p)) and p < ALPHA


def _verdict(better: bool, p: Optional[float]) -> str:
    """holds (better and significant), reversed (worse and significant) or level."""
    if not _significant(p):
        return "level"
    return "holds" if better else "reversed"


def _better(quantity: str, comps: float, other: float) -> bool:
    """Whether CoMPS's mean is the better one: fewer iterations to success, a higher average return."""
    return comps < other if quantity == "iterations" else comps > other


_SHOWN = {"iterations": ("CoMPS", "{:.1f}", " iterations per task"),
          "mean_return": ("CoMPS average return", "{:.2f}", "")}
"""How the claims table writes the means of a quantity: (CoMPS's label, the number's format, the unit)."""


def _ahead_of_all(results: dict, quantity: str) -> dict:
    """CoMPS better than every other method on ``quantity``: holds if it is against each, reversed if any is
    better than CoMPS (``methods``: those), level otherwise (``methods``: those level with it)."""
    comps = per_seed(results, "comps", quantity)
    tests = {m: statistics.significance(comps, per_seed(results, m, quantity))
             for m in results["methods"] if m != "comps"}
    if not tests:
        return {"verdict": "n/a", "shows": "no other method ran"}
    each = {m: _verdict(_better(quantity, t["mean_a"], t["mean_b"]), t["p_ttest"]) for m, t in tests.items()}
    verdict = ("reversed" if "reversed" in each.values() else
               "holds" if all(v == "holds" for v in each.values()) else "level")
    label, number, unit = _SHOWN[quantity]
    shows = f"{label} {number.format(comps.mean())}{unit}; " + ", ".join(
        f"{m} {number.format(t['mean_b'])} (p {_p(t['p_ttest'])})" for m, t in tests.items())
    return {"verdict": verdict, "shows": shows, "methods": [m for m, v in each.items() if v == verdict]}


def _faster_with_tasks(results: dict) -> dict:
    its = _floats(results["methods"]["comps"]["iterations_to_success"])
    n = its.shape[1]
    if n < 2:
        return {"verdict": "n/a", "shows": "one task"}
    half = n // 2
    first, second = its[:, :half].mean(1), its[:, half:].mean(1)
    p = _paired_p(first, second)
    return {"verdict": _verdict(second.mean() < first.mean(), p),
            "shows": f"CoMPS tasks 1-{half}: {first.mean():.1f}, tasks {half + 1}-{n}: {second.mean():.1f} "
                     f"iterations per task (paired t-test over seeds, p {_p(p)})"}


def _paired_p(x: np.ndarray, y: np.ndarray) -> Optional[float]:
    """The two-sided paired t-test's p of x against y (None with fewer than two pairs). Differences that are all
    equal get the test's limit, without scipy's warning: 1 if they are 0, else 0."""
    from scipy import stats

    d = x - y
    if len(d) < 2:
        return None
    if np.all(d == d[0]):
        return 1.0 if d[0] == 0 else 0.0
    return float(stats.ttest_rel(x, y).pvalue)


def _ahead_of(results: dict, other: str, quantity: str) -> dict:
    if other not in results["methods"]:
        return {"verdict": "n/a", "shows": f"{other} did not run"}
    t = statistics.significance(per_seed(results, "comps", quantity), per_seed(results, other, quantity))
    label, number, unit = _SHOWN[quantity]
    return {"verdict": _verdict(_better(quantity, t["mean_a"], t["mean_b"]), t["p_ttest"]),
            "shows": f"{label} {number.format(t['mean_a'])} against {other} {number.format(t['mean_b'])}{unit} "
                     f"(p {_p(t['p_ttest'])}, bootstrap {_p(t['p_bootstrap'])})"}


def _backward_transfer(results: dict) -> dict:
    bt = _floats(results["methods"]["comps"]["backward_transfer"])
    seeds = np.array([np.nanmean(row) if np.any(np.isfinite(row)) else np.nan for row in bt])
    seeds = seeds[np.isfinite(seeds)]
    if seeds.size == 0:
        return {"verdict": "n/a", "shows": "not measured (--backward-tasks 0, or one task)"}
    mean, se = float(seeds.mean()), float(seeds.std(ddof=1) / np.sqrt(seeds.size)) if seeds.size > 1 else 0.0
    verdict = "holds" if mean >= BACKWARD_STRONG else ("level" if mean > 0 else "reversed")
    return {"verdict": verdict, "shows": f"CoMPS normalized reward on its previous tasks {mean:.2f} ± {se:.2f} "
                                         f"(1: nothing forgotten; strong from {BACKWARD_STRONG})"}


_CHECKS = {"fastest": lambda r, c: _ahead_of_all(r, c.quantity),
           "faster_with_tasks": lambda r, c: _faster_with_tasks(r),
           "ahead_of_gmps_ppo": lambda r, c: _ahead_of(r, "gmps_ppo", c.quantity),
           "highest_return": lambda r, c: _ahead_of_all(r, c.quantity),
           "backward_transfer": lambda r, c: _backward_transfer(r)}
"""Each claim's check: (a sequence's merged results, what the paper says there) -> {"verdict", "shows", ...}."""


def claims_table(results_by_sequence: dict, family: str) -> list[dict]:
    """One row per check of ``jcomps.analysis.paper.CLAIMS`` and sequence run, with what the paper says of it on
    ``family``'s sequence (``paper.claim``; no row where it says nothing): {"claim", "text", "where", "sequence",
    "verdict" (holds, level, reversed, n/a; "not claimed" where the paper does not make the claim there),
    "shows" (this study's figures behind it, in every case), and for a claim against every other method "methods"
    (those behind its verdict)}."""
    rows = []
    for key, check in _CHECKS.items():
        for sequence, results in results_by_sequence.items():
            said = paper.claim(key, sequence, family)
            if said is None:
                continue
            found = check(results, said)
            if not said.made:
                found = {"verdict": "not claimed", "shows": found["shows"]}
            rows.append({"claim": key, "text": said.text, "where": said.where, "sequence": sequence, **found})
    return rows


def _p(p) -> str:
    if p is None or not np.isfinite(p):
        return "n/a"
    if p == 0:
        return "0"  # two constant groups apart
    return f"{p:.2g}" if p >= 1e-3 else f"{p:.1e}"


def _why_the_t_test() -> str:
    """Why the column *ours* and the verdicts use the analytic t-test, not the bootstrap the paper names: a
    bootstrap's p cannot go below 1/(resamples + 1), and most of the paper's p-values are below that."""
    floor = 1 / (statistics.BOOTSTRAP_SAMPLES + 1)
    published = [p for families in paper.P_VALUES.values() for ps in families.values() for p in ps.values()]
    return (f"The column *ours*, and every verdict of the claims table, is the analytic t-test's p: a bootstrap of "
            f"{statistics.BOOTSTRAP_SAMPLES:,} resamples cannot give a p below 1/{statistics.BOOTSTRAP_SAMPLES + 1:,}"
            f" ≈ {floor:.1e}, and {sum(p < floor for p in published)} of the paper's {len(published)} p-values are "
            f"below it.")


def markdown(family: str, proto: Protocol, results_by_sequence: dict, partial: Optional[dict] = None) -> str:
    """The study's report: the protocol, per sequence the p-value table beside the paper's, the claims table."""
    name = paper.FAMILIES.get(family)
    lines = [f"# Reproducing the paper on {family}" + (f" (the paper's {name})" if name else " (not in the paper)"),
             "",
             f"Scale `{proto.scale}`: {', '.join(proto.methods)} on the {' and '.join(proto.sequences)} "
             f"sequence(s), {proto.num_tasks} tasks, {proto.seeds} seeds"
             + (f"; options for every run: `{' '.join(proto.extra)}`" if proto.extra else "") + "."]
    if partial:
        lines += ["", "**Partial**: the tasks every method of a sequence has finished: " + ", ".join(
            f"{s} {p['tasks']} of {p['of']}" for s, p in partial.items()) + "."]
    lines += ["", "Figures: `figures/figure3.png` (iterations to success per task, mean ± s.e. over seeds: the "
              "paper's Figure 3 on the stationary sequence, its appendix's figure of L784-791 on the non-stationary "
              "one), `figures/lifelong_return.png` (the return of every iteration over the sequence, averaged over 5 "
              "iterations and over seeds: the paper's Figure 4, left, on the non-stationary sequence)."]
    for sequence, results in results_by_sequence.items():
        lines += ["", f"## {sequence}", "", f"p-values of CoMPS against each method by the paper's test "
                  f"({paper.TEST}) over this study's {proto.seeds} seeds, each as the analytic t-test's and the "
                  f"bootstrap's. {_why_the_t_test()} The paper tests "
                  f"{'iterations to success' if paper.QUANTITY[sequence] == 'iterations' else 'the average return'}"
                  f" on this sequence; so does *ours*. Means are per-seed means over the sequence.", "",
                  "| CoMPS vs | iterations (CoMPS, other) | p, t-test / bootstrap | average return (CoMPS, other) "
                  "| p, t-test / bootstrap | ours | the paper's |", "|---|---|---|---|---|---|---|"]
        for row in p_value_table(results, family, sequence):
            it, ret = row["iterations"], row["mean_return"]
            ours = row[row["quantity"]]["p_ttest"]
            lines.append(f"| {row['method']} | {it['mean_a']:.1f}, {it['mean_b']:.1f} | {_p(it['p_ttest'])} / "
                         f"{_p(it['p_bootstrap'])} | {ret['mean_a']:.2f}, {ret['mean_b']:.2f} | "
                         f"{_p(ret['p_ttest'])} / {_p(ret['p_bootstrap'])} | {_p(ours)} | "
                         f"{_p(row['paper_p']) if row['paper_p'] is not None else '–'} |")
    lines += ["", "## The paper's claims", "", f"holds: in the claim's direction with p < {ALPHA} (the t-test's); "
              f"reversed: against it with p < {ALPHA}; level: neither; not claimed: the paper does not make the claim "
              "of this sequence or family (the row says what it says instead; what this study shows is given all "
              "the same). A claim against every other method holds if it holds against each, and is reversed if any "
              f"is ahead of CoMPS with p < {ALPHA}. Ours, not the paper's: the paired t-test over seeds (the first "
              "half of the tasks against the second) behind \"faster as more tasks are experienced\", and the "
              f"threshold {BACKWARD_STRONG} of \"strong\" backward transfer.", "",
              "| claim | where | sequence | this study | what it shows |", "|---|---|---|---|---|"]
    for row in claims_table(results_by_sequence, family):
        lines.append(f"| {row['text']} | {row['where']} | {row['sequence']} | **{row['verdict']}** | {row['shows']} |")
    return "\n".join(lines) + "\n"


def figures(results_by_sequence: dict, directory: str, family: str) -> list[str]:
    """The Figure-3 panel (iterations to success per task, per method, mean ± s.e., one panel per sequence) and
    the lifelong-return panel (every iteration's return over the sequence, the mean of 5 consecutive iterations,
    averaged over the seeds while all run, with ± s.e.) of ``family`` into ``directory``; returns the paths."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    os.makedirs(directory, exist_ok=True)
    written = []
    n = len(results_by_sequence)

    def save(fig, name):
        path = os.path.join(directory, name)
        fig.savefig(path + ".tmp.png", dpi=110, bbox_inches="tight")
        os.replace(path + ".tmp.png", path)
        written.append(path)

    fig = Figure(figsize=(6 * n, 4))
    axes = np.atleast_1d(fig.subplots(1, n))
    for ax, (sequence, results) in zip(axes, results_by_sequence.items()):
        for k, (name, m) in enumerate(results["methods"].items()):
            its = _floats(m["iterations_to_success"])
            mean, se = statistics.mean_se(its)
            ax.errorbar(np.arange(1, its.shape[1] + 1), mean, yerr=se, marker="o", ms=3, capsize=2, color=f"C{k}",
                        label=name)
        ax.set(xlabel="task i", ylabel="iterations to success (fewer is better)",
               title=f"{family}, {sequence}")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.legend(fontsize=8)
    save(fig, "figure3.png")

    fig = Figure(figsize=(6 * n, 4))
    axes = np.atleast_1d(fig.subplots(1, n))
    for ax, (sequence, results) in zip(axes, results_by_sequence.items()):
        for k, (name, m) in enumerate(results["methods"].items()):
            lines = [np.concatenate([np.asarray(c, np.float64) for c in seed]) for seed in m["return_curves"]]
            window = 5 if min(len(x) for x in lines) >= 5 else 1  # a sequence shorter than 5 iterations: as is
            length = min(len(x) for x in lines) // window * window
            smoothed = np.stack([x[:length].reshape(-1, window).mean(1) for x in lines])
            mean, se = statistics.mean_se(smoothed)
            x = np.arange(1, len(mean) + 1) * window
            ax.plot(x, mean, color=f"C{k}", label=name)
            ax.fill_between(x, mean - se, mean + se, color=f"C{k}", alpha=0.2)
        ax.set(xlabel="iteration of the sequence", ylabel="return (mean of 5 iterations)",
               title=f"Lifelong return, {sequence}")
        ax.legend(fontsize=8)
    save(fig, "lifelong_return.png")
    return written
