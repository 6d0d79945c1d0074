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
import dataclasses
import os
import shutil
import sys

from jcomps.analysis import report
from jcomps.runner import distributed, results, rundir
from jcomps.runner.description import RunDescription
from jcomps.runner.files import RunError


def _agreed(description: RunDescription) -> dict:
    """What the sources of one study must agree on, as JSON: everything but the methods, their configs and
    overrides, the chunking, the process count and the checkpoints' format (none changes the results)."""
    out = description.to_json()
    for key in ("methods", "overrides", "processes", "format"):
        out.pop(key, None)
    out["run"] = {k: v for k, v in out["run"].items() if k not in ("methods", "chunk_tasks", "chunk_tasks_by_method")}
    return out


def merged_description(descriptions: list) -> RunDescription:
    """The description of the merged study from the sources' ([(directory, RunDescription)]); raises RunError
    naming what differs."""
    dirs = [d for d, _ in descriptions]
    first = descriptions[0][1]
    names, configs, overrides, chunks = [], {}, {}, {}
    for d, desc in descriptions:
        diff = rundir.differences(_agreed(first), _agreed(desc))
        if diff:
            raise RunError(f"{d} is not the same study as {dirs[0]}: " + "; ".join(diff[:4]))
        for name in desc.run.methods:
            if name in configs:
                raise RunError(f"method {name} is in more than one source ({d} and an earlier one); "
                               "merge runs of different methods")
            names.append(name)
            configs[name] = desc.methods[name]
            chunks[name] = (desc.chunk_tasks_by_method or {}).get(name, desc.run.chunk_tasks)
            if name in desc.overrides:
                overrides[name] = desc.overrides[name]
    processes = {desc.processes for _, desc in descriptions}
    return dataclasses.replace(
        first, run=dataclasses.replace(first.run, methods=tuple(names)), methods=configs, overrides=overrides,
        chunk_tasks_by_method=chunks if len(set(chunks.values())) > 1 else None,
        # sources spread differently: the merged directory is not resumed
        processes=processes.pop() if len(processes) == 1 else None)


def merge(out: str, sources: list[str], baseline=None, methods_=None, partial: bool = False) -> dict:
    """Writes the merged study into ``out`` (a new directory) and its report; returns the report's results.
    ``methods_`` (default: all) takes only these methods from the sources, e.g. the finished ones of a run whose
    later methods are still going. With ``partial``, methods that have not finished bring the tasks they have
    finished, and the report covers the tasks every method has finished (``report.read_raws``)."""
    if os.path.exists(rundir.path(out)):
        raise RunError(f"{out} already holds a run; merge into a new directory")
    descriptions = [(d, rundir.read(d)) for d in sources]
    if methods_:
        found = [m for _, desc in descriptions for m in desc.run.methods]
        missing = [m for m in methods_ if m not in found]
        if missing:
            raise RunError(f"--methods {' '.join(missing)}: not in the sources; they have {', '.join(found)}")
        descriptions = [(d, desc.only(methods_)) for d, desc in descriptions if set(desc.run.methods) & set(methods_)]
    description = merged_description(descriptions)
    copies = []
    for d, desc in descriptions:
        for _, entry, _ in desc.entries():
            if results.load(d, entry) is not None:
                copies.append((results.path(d, entry), results.path(out, entry)))
            elif partial and results.load_partial(d, entry) is not None:
                copies.append((results.partial_path(d, entry), results.partial_path(out, entry)))
            else:
                raise RunError(f"{d}: {entry} has not finished; continue it with --resume first"
                               + ("" if partial else ", or merge the tasks done so far with --partial"))
    for src, dst in copies:
        os.makedirs(os.path.dirname(dst), exist_ok=True)
        shutil.copy2(src, dst)
    os.makedirs(out, exist_ok=True)
    rundir.write(out, description)
    return report.write(out, baseline=baseline, partial=partial)


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
