"""Files written safely: atomic writes through a temporary file and a rename, JSON records.

Model files (``save_model``, ``load_model``) are in :mod:`snds.models`.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["atomic_write", "remove_temporaries", "to_jsonable", "write_json"]


def atomic_write(path: Path, write: Any) -> None:
    """Writes a file through a temporary file in the same folder and an atomic rename.

    An interrupted write leaves either the old file or none, never a half-written one.

    Arguments:
        path: The destination.
        write: A function that writes to the temporary path it is given.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        write(Path(tmp))
        # mkstemp creates the file private (0600); give it the mode a plain open() would.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def remove_temporaries(directory: Path) -> None:
    """Removes the temporary files that :func:`atomic_write` left in ``directory`` when killed.

    Only for a folder that one process writes at a time (a model directory being trained).
    """
    directory = Path(directory)
    if directory.is_dir():
        for path in directory.glob(".*.tmp"):
            path.unlink(missing_ok=True)


def write_json(path: Path, data: dict) -> None:
    """Writes JSON atomically, with sorted keys and an indent for diffs."""

    def write(tmp: Path) -> None:
        tmp.write_text(json.dumps(data, indent=2, sort_keys=True, allow_nan=True) + "\n")

    atomic_write(path, write)


def to_jsonable(value: Any) -> Any:
    """Converts NumPy scalars and arrays inside a record to plain JSON types."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value
