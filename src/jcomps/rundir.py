"""The files of a run directory that are plain JSON: written whole or not at all."""

from __future__ import annotations

import json
import os


def write_json(path: str, data) -> None:
    """Writes ``data`` as JSON to ``path`` atomically (a temporary file renamed over it): a reader, or a run killed
    mid-write, sees the old file or the new one, never half of one."""
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(data, f, indent=1)
    os.replace(tmp, path)
