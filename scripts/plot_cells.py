"""Iterations to success per task of several finished runs, one line per run, one panel per group: the figures of
the studies in docs/results.md that compare settings run as separate run directories (issue 58's cells).

    python scripts/plot_cells.py --out docs/figures/i58_hc.png --xlabel "task" \
        --panel "Half-Cheetah, CoMPS" "learnt std=docs/studies/cheetah_vel-2x2/learnt-comps" \
                "fixed 0.15, 20x50 (2 seeds)=docs/studies/cheetah_vel-budget/b20x50-comps" \
        --panel "Half-Cheetah, GMPS+PPO+IS" ...

Each ``LABEL=DIR`` reads ``DIR/results.json`` (a run of one method; ``DIR:METHOD`` picks one of several) and draws
the mean over seeds of each task's iterations to success; the legend gives the mean over the tasks after the
first (``--from-task``), the tasks that follow a meta step.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np


def read_cell(spec: str) -> tuple[str, np.ndarray]:
    """``LABEL=DIR[:METHOD]`` -> (label, iterations to success [seeds, tasks])."""
    if "=" not in spec:
        raise ValueError(f"{spec!r}: expected LABEL=DIR or LABEL=DIR:METHOD")
    label, where = spec.split("=", 1)
    directory, _, method = where.partition(":")
    path = os.path.join(directory, "results.json")
    try:
        with open(path) as f:
            entries = json.load(f)["methods"]
    except (OSError, ValueError, KeyError) as err:
        raise ValueError(f"{path}: cannot read a run's results ({err})") from None
    if not method:
        if len(entries) != 1:
            raise ValueError(f"{path} holds {sorted(entries)}: name one as {label}={directory}:METHOD")
        (method,) = entries
    if method not in entries:
        raise ValueError(f"{path} has no method {method!r} (it has {sorted(entries)})")
    return label, np.asarray(entries[method]["iterations_to_success"], dtype=np.float64)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, help="the figure's file (.png)")
    parser.add_argument("--panel", nargs="+", action="append", required=True, metavar="TITLE LABEL=DIR",
                        help="a panel: its title, then one LABEL=DIR[:METHOD] per line")
    parser.add_argument("--xlabel", default="task")
    parser.add_argument("--from-task", type=int, default=2, help="the legend's mean starts at this task (1-based)")
    parser.add_argument("--log", action="store_true", help="a logarithmic y axis")
    args = parser.parse_args(argv)
    try:
        panels = [(title, [read_cell(spec) for spec in specs]) for title, *specs in args.panel]
        for title, cells in panels:
            if not cells:
                raise ValueError(f"--panel {title!r} has no LABEL=DIR after its title")
    except ValueError as err:
        print(f"plot_cells.py: error: {err}", file=sys.stderr)
        return 2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(7.2 * len(panels), 4.8), squeeze=False)
    for ax, (title, cells) in zip(axes[0], panels):
        for label, its in cells:
            tasks = np.arange(1, its.shape[1] + 1)
            later = its[:, args.from_task - 1:].mean()
            ax.plot(tasks, its.mean(axis=0), marker="o", label=f"{label}: {later:.1f}")
        ax.set_title(f"{title} (legend: mean over tasks {args.from_task}-{its.shape[1]})")
        ax.set_xlabel(args.xlabel)
        ax.set_ylabel("iterations to success (mean over seeds)")
        ax.set_xticks(tasks)
        if args.log:
            ax.set_yscale("log")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out, dpi=100)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
