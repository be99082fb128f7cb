"""Benchmark sweeps: methods x motions x seeds, resumable, on local cores or a Dask cluster.

A sweep is a list of :class:`Task` (:mod:`snds.benchmark.tasks`). Each task trains and
evaluates one policy in one process with one torch thread (:func:`run_task`,
:mod:`snds.benchmark.runner`) and gives one flat row. :func:`run_sweep`
(:mod:`snds.benchmark.sweep`) appends every finished row to ``results.jsonl`` at once
(flushed and fsynced, :mod:`snds.benchmark.results`), so an interrupted sweep loses at most
the tasks that were running; rerunning it into the same folder skips the tasks already
there. At the end it writes ``results.csv`` and ``summary.md``
(:mod:`snds.benchmark.summary`), and :func:`plot_benchmark` draws the figures
(:mod:`snds.benchmark.figures`).

    rows = run_sweep(make_tasks(["Sine"], ["snds", "bc"], seeds=3), out=Path("runs/b"))
    plot_benchmark(rows, Path("runs/b"))
"""

from __future__ import annotations

from snds.benchmark.figures import benchmark_figures, plot_benchmark
from snds.benchmark.results import (
    RESULTS_FILE,
    ROW_FIELDS,
    SETTINGS_FILE,
    finished_rows,
    write_csv,
)
from snds.benchmark.runner import TaskOutput, run_batch, run_task
from snds.benchmark.summary import PAPER_SNDS_MSE, summarise
from snds.benchmark.sweep import run_sweep
from snds.benchmark.tasks import (
    MODELS_DIR,
    MOTION_GROUPS,
    SweepSettings,
    Task,
    make_tasks,
    resolve_methods,
    resolve_motions,
)

__all__ = [
    "MODELS_DIR",
    "MOTION_GROUPS",
    "PAPER_SNDS_MSE",
    "RESULTS_FILE",
    "ROW_FIELDS",
    "SETTINGS_FILE",
    "SweepSettings",
    "Task",
    "TaskOutput",
    "benchmark_figures",
    "finished_rows",
    "make_tasks",
    "plot_benchmark",
    "resolve_methods",
    "resolve_motions",
    "run_batch",
    "run_sweep",
    "run_task",
    "summarise",
    "write_csv",
]
