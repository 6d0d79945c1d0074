"""The run directory's plain JSON files, written whole or not at all, and read with an error that names the file.
Nothing here imports JAX: the runner reads the device count of a run it resumes before JAX starts
(``stored_devices``)."""

from __future__ import annotations

import json
import os
from typing import Optional


class RunError(ValueError):
    """A run directory that cannot be used as asked (a clash with another run, a resume that does not match, an
    unreadable file): the message says what to do."""


def write_json(path: str, data) -> None:
    """Writes ``data`` as JSON to ``path`` atomically (a temporary file renamed over it): a reader, or a run killed
    mid-write, sees the old file or the new one, never half of one."""
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(data, f, indent=1)
    os.replace(tmp, path)


def read_json(path: str) -> dict:
    """The JSON object in ``path``; RunError naming the file when it cannot be read or is not one (a truncated or
    hand-edited file)."""
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


RUN_JSON = "run.json"
"""The file of a run directory that describes its run (``jcomps.runner.description.RunDescription``)."""


def stored_devices(out: str) -> Optional[int]:
    """The device count recorded in run directory ``out`` (over every process), None where there is none to read:
    what a resume sets up before JAX starts (float rounding depends on it). The run's description is read, and a
    missing or unreadable one reported, by ``jcomps.runner.rundir.read`` once JAX runs."""
    try:
        devices = read_json(os.path.join(out, RUN_JSON)).get("devices")
    except RunError:
        return None
    return devices if isinstance(devices, int) and not isinstance(devices, bool) else None
