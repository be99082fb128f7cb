"""A sweep's results folder: append-only JSON lines of result rows, the settings they share,
and the CSV table.

``results.jsonl`` gets one row per finished run, flushed and fsynced at once, so that a kill
loses at most the runs in progress; a torn last line is dropped when the file is read back.
"""

from __future__ import annotations

import csv
import json
import os
from collections.abc import Sequence
from pathlib import Path

from snds.benchmark.tasks import Task
from snds.errors import SNDSError
from snds.io import atomic_write

__all__ = [
    "RESULTS_FILE",
    "ROW_FIELDS",
    "SETTINGS_FILE",
    "append_row",
    "check_settings",
    "finished_rows",
    "read_results",
    "write_csv",
]

#: The columns of a result row, in the order of ``results.csv``.
ROW_FIELDS: tuple[str, ...] = (
    "motion",
    "method",
    "seed",
    "demos",
    "se3",
    "train_seconds",
    "train_cpu_seconds",
    "velocity_mse",
    "velocity_mse_paper",
    "velocity_error_relative",
    "dtw",
    "dtw_paper",
    "final_distance",
    "angle_error_along",
    "final_angle_error",
    "converged_fraction",
    "decrease_violations",
    "samples_checked",
    "median_time_to_converge",
    "shortened_fraction",
    "largest_safe_dt",
    "peak_memory_mb",
)

#: The sweep settings that change results; a folder holds results of one setting only.
SETTINGS_FILE = "sweep.json"
#: The result rows, one JSON object a line, in the order the runs finished.
RESULTS_FILE = "results.jsonl"


def read_results(path: Path) -> dict[str, dict]:
    """Rows of ``results.jsonl`` by task key; drops a torn last line left by a kill."""
    if not path.is_file():
        return {}
    rows: dict[str, dict] = {}
    good: list[str] = []
    text = path.read_text()
    for line in text.splitlines():
        try:
            row = json.loads(line)
            rows[Task.from_row(row).key] = row
            good.append(line)
        except (json.JSONDecodeError, KeyError, TypeError, ValueError):
            continue
    if text and (not text.endswith("\n") or len(good) != len(text.splitlines())):
        # Appending after a torn line would glue the next row to it: rewrite the good ones.
        atomic_write(path, lambda tmp: tmp.write_text("".join(f"{g}\n" for g in good)))
    return rows


def finished_rows(out: Path) -> dict[str, dict]:
    """The result rows already in a sweep folder, by :attr:`Task.key`."""
    return read_results(Path(out) / RESULTS_FILE)


def append_row(path: Path, row: dict) -> None:
    """Appends a row to ``results.jsonl``, on disk (flushed and fsynced) when it returns."""
    with open(path, "a") as handle:
        handle.write(json.dumps(row) + "\n")
        handle.flush()
        os.fsync(handle.fileno())


def check_settings(out: Path, settings: dict) -> None:
    """Records a sweep's settings in ``out``, or refuses them if the folder holds results of
    other settings.

    Raises:
        SNDSError: ``out`` holds a sweep of other settings (the message names both).
    """
    path = out / SETTINGS_FILE
    if path.is_file():
        previous = json.loads(path.read_text())
        if previous != settings:
            raise SNDSError(
                f"{out} holds results of a sweep with {previous}, this one has {settings}; "
                "use another --out"
            )
    else:
        atomic_write(path, lambda tmp: tmp.write_text(json.dumps(settings) + "\n"))


def write_csv(rows: Sequence[dict], path: Path) -> None:
    """Writes rows as CSV with the columns :data:`ROW_FIELDS`, atomically."""

    def write(tmp: Path) -> None:
        with open(tmp, "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(ROW_FIELDS), extrasaction="ignore")
            writer.writeheader()
            writer.writerows(rows)

    atomic_write(path, write)
