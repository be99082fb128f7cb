"""Running a sweep: the tasks not yet in its folder, on local cores or a Dask cluster, each
finished run stored at once, then the CSV table and the summary.

An interrupted sweep loses at most the runs in progress; run again into the same folder it
skips the tasks already there (:mod:`snds.benchmark.results`).
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

from snds.benchmark.results import (
    RESULTS_FILE,
    append_row,
    check_settings,
    read_results,
    write_csv,
)
from snds.benchmark.runner import TaskOutput, run_batch, run_task
from snds.benchmark.summary import summarise
from snds.benchmark.tasks import SweepSettings, Task, check_task, resolve_motions
from snds.errors import SNDSError
from snds.io import atomic_write
from snds.methods import get_method
from snds.parallel import starmap_unordered
from snds.runs import RunFolder

__all__ = ["run_sweep"]


def _units(tasks: Sequence[Task], batch_fits: int) -> list[tuple[Task, ...]]:
    """The tasks grouped into the runs of one worker call: up to ``batch_fits`` tasks of one
    motion, method and number of demonstrations where the method fits several at once
    (SNDS, BC), every other task alone; in the order of ``tasks``."""
    units: list[list[Task]] = []
    filling: dict[tuple, list[Task]] = {}
    for task in tasks:
        if batch_fits == 1 or not hasattr(get_method(task.method), "fit_many"):
            units.append([task])
            continue
        group = (task.motion, task.method, task.demos, task.se3)
        unit = filling.get(group)
        if unit is None or len(unit) == batch_fits:
            unit = filling[group] = []
            units.append(unit)
        unit.append(task)
    return [tuple(unit) for unit in units]


def _run_unit(unit: tuple[Task, ...], settings: SweepSettings) -> list[TaskOutput]:
    return [run_task(unit[0], settings)] if len(unit) == 1 else run_batch(unit, settings)


def _run_units(
    units: Sequence[tuple[Task, ...]], *, jobs: int, scheduler: str | None, settings: SweepSettings
) -> Iterator[TaskOutput]:
    """The outputs of the units' runs as they finish: in this process (``jobs == 1``), on a
    local process pool or on a Dask cluster (:func:`snds.parallel.starmap_unordered`)."""
    calls = [(unit, settings) for unit in units]
    keys = ["+".join(task.key for task in unit) for unit in units]
    for _, outputs in starmap_unordered(
        _run_unit, calls, jobs=jobs, scheduler=scheduler, keys=keys
    ):
        yield from outputs


def _store(out: Path, output: TaskOutput) -> None:
    """Writes a run's model, then appends its row: a row on disk always has its model."""
    RunFolder(out / Task.from_row(output.row).model_dir).write_files(output.model)
    append_row(out / RESULTS_FILE, output.row)


def run_sweep(
    tasks: Iterable[Task],
    *,
    out: Path,
    settings: SweepSettings | None = None,
    jobs: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
) -> list[dict]:
    """Runs the tasks not yet in ``out`` and writes the results.

    Each finished run's model goes to ``out/models/...`` (see :attr:`Task.model_dir`) and its
    row is appended to ``out/results.jsonl`` at once; tasks whose key is already there are
    skipped, so an interrupted sweep resumes where it stopped. A folder holds the results of
    one :class:`SweepSettings` (recorded in ``sweep.json``); mixing them is refused. At the
    end ``results.csv`` and ``summary.md`` cover the given tasks.

    Arguments:
        tasks: The runs.
        out: The results folder (created if needed).
        settings: What the runs share (default: :class:`SweepSettings` ()).
        jobs: Local worker processes (default: all cores; 1 runs in this process).
        scheduler: A Dask scheduler address such as ``tcp://host:8786``; runs there instead.
        progress: Show a progress bar (only on a terminal).

    Returns:
        One row per task, in the order of ``tasks``.
    """
    from tqdm.auto import tqdm

    settings = settings or SweepSettings()
    tasks = list(dict.fromkeys(tasks))
    jobs = jobs or os.cpu_count() or 1
    if jobs < 1:
        raise SNDSError(f"jobs must be >= 1, got {jobs}")
    for task in tasks:
        check_task(task)
        resolve_motions(task.motion)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    check_settings(out, settings.to_dict())
    done = read_results(out / RESULTS_FILE)
    pending = [task for task in tasks if task.key not in done]
    units = _units(pending, settings.batch_fits)
    outputs = _run_units(units, jobs=jobs, scheduler=scheduler, settings=settings)
    show = progress and sys.stderr.isatty()
    start = time.perf_counter()
    with tqdm(
        total=len(tasks),
        initial=len(tasks) - len(pending),
        disable=not show,
        desc="benchmark",
        unit="run",
    ) as bar:
        for output in outputs:
            _store(out, output)
            row = output.row
            done[Task.from_row(row).key] = row
            bar.set_postfix_str(f"{row['motion']}/{row['method']}", refresh=False)
            bar.update()
    ordered = [done[task.key] for task in tasks]
    write_csv(ordered, out / "results.csv")
    summary = summarise(ordered)
    seconds = time.perf_counter() - start
    header = (
        f"# Benchmark\n\n{len(tasks)} runs ({len(pending)} new, {seconds:.0f} s); "
        f"steps {settings.steps or 'default'}; stability check of {settings.rollouts} "
        f"rollouts and {settings.samples} decrease samples per run.\n\n"
    )
    atomic_write(out / "summary.md", lambda tmp: tmp.write_text(header + summary))
    return ordered
