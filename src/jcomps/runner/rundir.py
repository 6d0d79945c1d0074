"""A run directory's ``run.json``: the one reader and writer of a run's description
(``jcomps.runner.description.RunDescription``), and the check that a resume continues the very run it holds.

``read`` gives the description as every version of jcomps wrote it (``description.from_json`` fills what older
ones lacked); ``write`` writes it whole or not at all. ``open_run_dir`` creates the directory of a new run, or on
``--resume`` compares the stored run with the one asked for, field by field, and records the fields it filled.
"""

from __future__ import annotations

import os

from jcomps.runner import distributed
from jcomps.runner.description import RunDescription, from_json
from jcomps.runner.files import RUN_JSON, RunError, read_json, write_json


def path(out: str) -> str:
    """The ``run.json`` of run directory ``out``."""
    return os.path.join(out, RUN_JSON)


def read(out: str) -> RunDescription:
    """The description of the run in directory ``out``; RunError naming the file when there is none, or it cannot
    be read or holds no run description."""
    run_json = path(out)
    if not os.path.isfile(run_json):
        raise RunError(f"{out} holds no run (no {RUN_JSON})")
    return from_json(read_json(run_json), run_json)


def write(out: str, description: RunDescription) -> None:
    """Writes ``description`` as the ``run.json`` of ``out`` (an existing directory), atomically."""
    write_json(path(out), description.to_json())


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


def _check_resumable(out: str, asked: RunDescription) -> None:
    """Checks that ``out`` holds the run ``asked`` describes (RunError naming the differences, or why this version
    cannot resume it); fields its ``run.json`` lacked are recorded there."""
    if not os.path.isfile(path(out)):
        raise RunError(f"--resume: {out} holds no run (no {RUN_JSON}); start it without --resume")
    stored = read(out)
    if stored.unresumable:
        raise RunError(f"--resume: {out} was made by an earlier version of jcomps and cannot be resumed by this one "
                       f"({stored.unresumable}); start it anew with another --out (its finished tasks stay "
                       f"reportable: python experiments/report.py {out} --partial)")
    diff = differences(stored.to_json(), asked.to_json())
    devices, processes = stored.devices, stored.processes or 1
    per_process = (f"--devices {devices}" if processes == 1 else
                   f"--devices {devices // processes} on each of {processes} processes")
    hints = {"devices:": f" (float rounding depends on it: resume with {per_process})",
             "processes:": f" (each process restores its own members: resume with --num-processes {processes}"
                           f"{'' if processes != 1 else ', i.e. one process'})"}
    diff = [d + next((h for k, h in hints.items() if d.startswith(k)), "") for d in diff]
    if diff:
        raise RunError(f"--resume: {out} was made with another config: " + "; ".join(diff[:8]))
    if stored.filled and distributed.is_writer():  # record them, so that the run's description is whole again
        write(out, stored)


def open_run_dir(out: str, description: RunDescription, resume: bool) -> None:
    """Creates ``out`` for a new run (its ``run.json``: ``description``), or checks that it holds this very run when
    resuming; raises ``RunError`` saying what to do when it cannot. With several processes
    (``jcomps.runner.distributed``) every process checks, then process 0 writes while the others wait (they read the
    directory next)."""
    if resume:
        _check_resumable(out, description)
        distributed.barrier("run directory checked")
        return
    if os.path.exists(path(out)) or os.path.exists(os.path.join(out, "results.json")):
        raise RunError(f"{out} already holds a run; choose another --out, or add --resume to continue it")
    distributed.barrier("run directory checked")
    error = None
    if distributed.is_writer():
        try:
            os.makedirs(out, exist_ok=True)
            write(out, description)
        except OSError as err:
            error = (f"--out {out}: cannot create the run directory there ({type(err).__name__}: "
                     f"{err.strerror or err}); choose a writable path")
    if not distributed.all_agree(error is None, "creating the run directory"):
        raise RunError(error or f"--out {out}: process 0 could not create the run directory there")
