"""Merge run directories that ran different methods of the same study into one, and write its report.

Methods of one study can run in separate processes, e.g. side by side on one GPU, where a method alone leaves
the GPU mostly idle, or on different machines: give each its own ``--out`` with the same options apart from
``--methods``, then merge. Everything but the methods, the chunking and the process count must agree (family,
sequence, seeds, tasks, evaluation, grid, device count); the methods must not overlap and must have finished
(``--partial``: or have finished a chunk, and the report covers the tasks every method has finished). Chunking
may differ (a slow method checkpointing after every task beside others in chunks of 5: the methods' results do not
depend on it); held-out measurements are then at each method's own chunk boundaries, which the report plots as they are,
and the merged ``run.json`` lists each method's ``chunk_tasks`` under ``run.chunk_tasks_by_method``. The merged
directory gets ``run.json`` and ``raw/``, then ``results.json``, the plots and ``significance.md`` as if one run
had run them all (checkpoints stay in the sources); a source that ran ``ppo`` (from scratch) gives every method's
forward transfer its reference.

    python experiments/merge_runs.py runs/hc20 runs/hc20-a runs/hc20-b [--baseline ppo_tl] [--methods comps ppo_tl]
    python experiments/merge_runs.py runs/ag10 runs/ag10-comps runs/ag10-ppo_tl --partial   # studies still going
"""

from __future__ import annotations

import argparse
import os
import sys

from jcomps.analysis.merge import merge
from jcomps.runner import distributed
from jcomps.runner.files import RunError


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", help="the merged run directory (new)")
    parser.add_argument("sources", nargs="+", help="run directories written by experiments/run_sequence.py")
    parser.add_argument("--baseline", default=None, metavar="METHOD",
                        help="the method the significance table compares every other one with (default: comps)")
    parser.add_argument("--methods", nargs="+", default=None,
                        help="take only these methods from the sources (default: all; e.g. the finished ones)")
    parser.add_argument("--partial", action="store_true",
                        help="merge unfinished runs too: the report covers the tasks every method has finished")
    distributed.add_args(parser)
    args = parser.parse_args(argv)
    if not distributed.tool_process(args, parser):
        return
    try:
        merge(args.out, args.sources, args.baseline, args.methods, args.partial)
    except RunError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    print(open(os.path.join(args.out, "significance.md")).read())
    print(f"wrote {args.out}/run.json, raw/, results.json, plots/ and significance.md")


if __name__ == "__main__":
    main()
