"""Merging run directories that ran different methods of the same study into one (``experiments/merge_runs.py``'s
work, and ``experiments/reproduce.py``'s when a study's methods ran apart): the merged ``run.json`` and ``raw/``,
then the report as if one run had run them all. Everything but the methods, the chunking and the process count
must agree; ``merge_runs.py``'s docstring says what merges and how.
"""

from __future__ import annotations

import dataclasses
import os
import shutil

from jcomps.analysis import report
from jcomps.runner import results, rundir
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
