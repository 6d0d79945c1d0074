"""The run directory's description of a run (``run.json``): written when a run starts, compared with the run asked
for when it resumes, and the plain JSON files of a run directory (written whole or not at all).

``run.json`` holds everything that defines a run: the run options, the evaluation options, every method's config,
the hyperparameter grid and the per-method ``--set`` overrides if any, and the device count. A resume must match
it, apart from method config fields that jcomps added after the run was made at their defaults (every added field
keeps the old behaviour by default), which are filled in; fields whose addition changed what checkpoints hold
(``UNRESUMABLE_BEFORE``, ``UNRESUMABLE_EVAL_BEFORE``) make an older run unresumable, as does a ``format`` older than
``FORMAT`` (what the metrics in its checkpoints hold).
"""

from __future__ import annotations

import dataclasses
import json
import os
from typing import TYPE_CHECKING, Optional

import jax

from jcomps import continual, methods
from jcomps.runner import distributed
from jcomps.runner import grid as grids
from jcomps.runner.checkpoint import RunError

if TYPE_CHECKING:
    from jcomps.runner.experiment import RunConfig


def write_json(path: str, data) -> None:
    """Writes ``data`` as JSON to ``path`` atomically (a temporary file renamed over it): a reader, or a run killed
    mid-write, sees the old file or the new one, never half of one."""
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(data, f, indent=1)
    os.replace(tmp, path)


def read_json(path: str) -> dict:
    """The JSON object in ``path`` (a run directory's ``run.json``); RunError naming the file when it cannot be read
    or is not one (a truncated or hand-edited file)."""
    try:
        with open(path) as f:
            data = json.load(f)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise RunError(f"{path} cannot be read ({err}); it is written by jcomps: restore it, or start the run "
                       "anew in another directory") from err
    if not isinstance(data, dict):
        raise RunError(f"{path} holds a {type(data).__name__}, not the object jcomps writes; restore it, or start "
                       "the run anew in another directory")
    return data


def _jsonable(x):
    if dataclasses.is_dataclass(x):
        return {f.name: _jsonable(getattr(x, f.name)) for f in dataclasses.fields(x)}
    if isinstance(x, (tuple, list)):
        return [_jsonable(v) for v in x]
    return x


FORMAT = 2
"""The format of what a run's checkpoints hold beyond its configs, recorded as ``run.json``'s ``format`` (runs
made before it was recorded are format 1); a resume refuses an older one (``FORMAT_CHANGES`` says why)."""
FORMAT_CHANGES = {
    2: "the RL step's per-iteration metrics now hold the critic's explained variance (issue 44), which its "
       "checkpoints lack",
}


def describe(run: RunConfig, eval_config: continual.EvalConfig, method_configs: dict, grid=(),
             overrides: Optional[dict] = None) -> dict:
    """The JSON description of a run (``run.json``), with the device count over every process (float rounding
    depends on it, so a resume must use the same count: ``experiments/run_sequence.py --resume`` takes it from
    here) and the process count (``jcomps.runner.distributed``: each process restores its own shards). With a
    hyperparameter grid, ``grid`` holds its axes in order (``jcomps.runner.grid.to_json``); with per-method overrides
    (``--set``), ``overrides`` holds them ({method: {"field.path": value}}, already part of the methods' configs);
    without either there is no such key."""
    out = {"run": _jsonable(run), "eval": _jsonable(eval_config),
           "methods": {name: _jsonable(method_configs[name]) for name in run.methods},
           "devices": jax.device_count(), "processes": jax.process_count(), "format": FORMAT}
    if grid:
        out["grid"] = grids.to_json(grid)
    if overrides:
        out["overrides"] = {m: {k: _jsonable(v) for k, v in values.items()} for m, values in overrides.items()}
    return out


def differences(a, b, prefix: str = "") -> list[str]:
    """What differs between two JSON descriptions ``a`` (the stored run) and ``b`` (the one asked for), one
    ``"<dotted path>: run has <a>, asked <b>"`` per leaf, nested dicts compared key by key (``prefix``: the path
    of ``a`` and ``b`` within their descriptions, ending in a dot)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for key in sorted(set(a) | set(b)):
            out += differences(a.get(key), b.get(key), f"{prefix}{key}.")
        return out
    return [] if a == b else [f"{prefix[:-1]}: run has {a!r}, asked {b!r}"]


# Config fields whose addition changed what a method's state holds, so that a run made before them cannot be
# resumed by this version whatever the options (its checkpoints no longer fit): field path within a method's
# config -> why.
UNRESUMABLE_BEFORE = {
    "meta.value_init": "CoMPS's meta step now keeps one value network per task and starts a new task's from the RL "
                       "step's critic (issue 27)",
    "context_source": "PEARL now keeps oyster's encoder buffers and weighs its KL per task (issue 28)",
    "kb_statistics": "PNC's knowledge base now pools its observation statistics over tasks (issue 28)",
    "meta.outer_loss": "the meta step now reports the inner step's gain per task slot, which its checkpoints lack "
                       "(issue 43)",
}

# The same for evaluation fields (``eval.<field>``), whose addition changed the metrics that checkpoints hold.
UNRESUMABLE_EVAL_BEFORE = dict.fromkeys(
    ("eval.learnt_eval", "eval.learnt_episodes"),
    "its checkpoints lack the evaluations of the learnt tasks behind forgetting and average performance (issue 28)")


def _fill_added_fields(stored: dict, asked: dict, default: dict, prefix: str) -> list[str]:
    """Config fields that a stored run lacks because jcomps added them after the run was made: where the asked
    value is the field's default (the behaviour the run had, as every added field keeps the old behaviour by
    default), ``stored`` gets it, in place. Returns the dotted paths filled; other differences are left for
    :func:`differences` to report."""
    filled = []
    for key, value in asked.items():
        if not isinstance(default, dict) or key not in default:
            continue
        if key not in stored:
            in_method = prefix.startswith("methods.")
            path = prefix.split(".", 2)[-1] + key if in_method else prefix + key
            why = (UNRESUMABLE_BEFORE if in_method else UNRESUMABLE_EVAL_BEFORE).get(path)
            if why is not None:
                raise RunError(f"--resume: this run was made before {prefix}{key} existed and cannot be resumed by "
                               f"this version ({why}); start it anew with another --out")
            if value == default[key]:
                stored[key] = value
                filled.append(prefix + key)
        elif isinstance(stored[key], dict) and isinstance(value, dict):
            filled += _fill_added_fields(stored[key], value, default[key], f"{prefix}{key}.")
    return filled


def _check_resumable(out: str, run_json: str, description: dict) -> None:
    """Checks that the run stored in ``run_json`` is the run ``description`` asks for (raises ``RunError`` naming
    the differences); fields added since the run was made, at their defaults, are filled into its ``run.json``."""
    if not os.path.isfile(run_json):
        raise RunError(f"--resume: {out} holds no run (no run.json); start it without --resume")
    stored = read_json(run_json)
    made = stored.get("format", 1)
    if isinstance(made, int) and made < FORMAT:
        why = "; ".join(FORMAT_CHANGES[f] for f in range(made + 1, FORMAT + 1))
        raise RunError(f"--resume: {out} was made by an earlier version of jcomps and cannot be resumed by this one "
                       f"({why}); start it anew with another --out (its finished tasks stay reportable: "
                       f"python experiments/report.py {out} --partial)")
    filled = []
    for name, config in description.get("methods", {}).items():
        if isinstance(stored.get("methods", {}).get(name), dict):
            stored["methods"][name] = methods.with_earlier_values(stored["methods"][name])
            default = _jsonable(methods.default_config(name, description["run"]["family"]))
            filled += _fill_added_fields(stored["methods"][name], config, default, f"methods.{name}.")
    if isinstance(stored.get("run"), dict) and isinstance(description.get("run"), dict):
        from jcomps.runner import experiment  # experiment imports this module

        filled += _fill_added_fields(stored["run"], description["run"], _jsonable(experiment.RunConfig()), "run.")
    if isinstance(stored.get("eval"), dict) and isinstance(description.get("eval"), dict):
        filled += _fill_added_fields(stored["eval"], description["eval"], _jsonable(continual.EvalConfig()), "eval.")
    if "processes" not in stored and "processes" in description:  # made before runs spread over processes
        stored["processes"] = 1
        filled.append("processes")
    diff = differences(stored, description)
    devices, processes = stored.get("devices"), stored.get("processes", 1)
    per_process = (f"--devices {devices}" if processes == 1 or not isinstance(devices, int) else
                   f"--devices {devices // processes} on each of {processes} processes")
    hints = {"devices:": f" (float rounding depends on it: resume with {per_process})",
             "processes:": f" (each process restores its own members: resume with --num-processes {processes}"
                           f"{'' if processes != 1 else ', i.e. one process'})"}
    diff = [d + next((h for k, h in hints.items() if d.startswith(k)), "") for d in diff]
    if diff:
        raise RunError(f"--resume: {out} was made with another config: " + "; ".join(diff[:8]))
    if filled and distributed.is_writer():  # record them, so that the run's description is whole again
        write_json(run_json, stored)


def open_run_dir(out: str, description: dict, resume: bool) -> None:
    """Creates ``out`` for a new run (its ``run.json``: ``description``), or checks that it holds this very run when
    resuming; raises ``RunError`` saying what to do when it cannot. With several processes
    (``jcomps.runner.distributed``) every process checks, then process 0 writes while the others wait (they read the
    directory next)."""
    run_json = os.path.join(out, "run.json")
    if resume:
        _check_resumable(out, run_json, description)
        distributed.barrier("run directory checked")
        return
    if os.path.exists(run_json) or os.path.exists(os.path.join(out, "results.json")):
        raise RunError(f"{out} already holds a run; choose another --out, or add --resume to continue it")
    distributed.barrier("run directory checked")
    error = None
    if distributed.is_writer():
        try:
            os.makedirs(out, exist_ok=True)
            write_json(run_json, description)
        except OSError as err:
            error = (f"--out {out}: cannot create the run directory there ({type(err).__name__}: "
                     f"{err.strerror or err}); choose a writable path")
    if not distributed.all_agree(error is None, "creating the run directory"):
        raise RunError(error or f"--out {out}: process 0 could not create the run directory there")
